// Unidirectional path tracer: BSDF sampling + next-event estimation combined
// with the power heuristic (Veach 1997, Ch. 9). max_depth and rr_depth have
// Mitsuba 3's meaning so the same file gives the same expected image:
// max_depth = longest path in segments (1: only directly visible emitters,
// -1: unbounded); Russian roulette from depth rr_depth with continuation
// probability min(max(beta) * eta^2, 0.95).
#pragma once

#include "integrators/integrator.h"

namespace mpg {

struct PathParams {
  int max_depth = -1;
  int rr_depth = 5;
  bool hide_emitters = false;
  int hard_depth_cap = 1024;  // safety net against unbounded loops (counted)
};

class PathIntegrator : public Integrator {
 public:
  explicit PathIntegrator(PathParams p) : p_(p) {}
  Color Li_hit(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si, PCG32& rng,
               Stats& stats) const override;

 private:
  PathParams p_;
};

}  // namespace mpg
