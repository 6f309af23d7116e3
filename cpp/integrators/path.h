// Unidirectional path tracer: BSDF sampling + next-event estimation combined
// with the power heuristic (Veach 1997, Ch. 9). max_depth and rr_depth have
// Mitsuba 3's meaning so the same file gives the same expected image:
// max_depth = longest path in segments (1: only directly visible emitters,
// -1: unbounded); Russian roulette from depth rr_depth with continuation
// probability min(max(beta) * eta^2, 0.95).
#pragma once

#include <memory>

#include "integrators/integrator.h"
#include "manifold/chain_estimator.h"

namespace mpg {

struct PathParams {
  int max_depth = -1;
  int rr_depth = 5;
  bool hide_emitters = false;
  // The light that reaches the camera through delta scattering only (the
  // emitters seen directly or in ideal glass and mirrors: no separator, so no
  // NEE or chain estimate has it): All keeps it, Exclude leaves it out, Only
  // renders it alone (the path ends at its first non-delta vertex). Exclude +
  // Only = All, path by path: a reference splits the work this way
  // (mpg-bench reference --camera-delta path); mpg's delta split traces extra
  // Only paths (Li_delta, Stats::split_delta).
  enum class CameraDelta { All, Exclude, Only };
  CameraDelta camera_delta = CameraDelta::All;
  int hard_depth_cap = 1024;  // safety net against unbounded loops (counted)
};

// With a ChainEstimator (integrators `sms` and `sms_star`) every separator also
// estimates the light through specular chains, and the BSDF-sampled paths the
// estimator owns are dropped (design.md, "No double counting").
class PathIntegrator : public Integrator {
 public:
  explicit PathIntegrator(PathParams p, std::shared_ptr<const ChainEstimator> chains = nullptr)
      : p_(p), chains_(std::move(chains)) {
    if (chains_ && !chains_->active()) chains_.reset();  // effects follow the scene
  }
  bool chains_active() const { return chains_ != nullptr; }
  // a point or spot chain light: rate 0 would lose its light (ChainEstimator::has_delta_lights)
  bool chains_delta_lights() const { return chains_ && chains_->has_delta_lights(); }
  const ChainEstimator* chains() const { return chains_.get(); }
  PathParams::CameraDelta camera_delta() const { return p_.camera_delta; }
  Color Li_hit(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si, PCG32& rng,
               Stats& stats) const override {
    return trace(scene, o, d, std::move(si), rng, stats, p_.camera_delta);
  }
  Color Li_delta(const Scene& scene, const Vec3& o, const Vec3& d, float tmin, float tmax, PCG32& rng,
                 Stats& stats) const override {
    stats.rays++;
    return trace(scene, o, d, scene.intersect(o, d, tmin, tmax), rng, stats, PathParams::CameraDelta::Only);
  }

 private:
  Color trace(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si, PCG32& rng,
              Stats& stats, PathParams::CameraDelta mode) const;
  PathParams p_;
  std::shared_ptr<const ChainEstimator> chains_;
};

}  // namespace mpg
