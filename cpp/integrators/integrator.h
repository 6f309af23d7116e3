// Integrator interface: radiance along one camera ray.
#pragma once

#include "core/rng.h"
#include "render/stats.h"
#include "scene/scene.h"

namespace mpg {

class LightTracer;

class Integrator {
 public:
  virtual ~Integrator() = default;
  // Radiance along a camera ray whose first hit `si` is already known.
  virtual Color Li_hit(const Scene& scene, const Vec3& o, const Vec3& d, SurfaceInteraction si,
                       PCG32& rng, Stats& stats) const = 0;
  Color Li(const Scene& scene, const Vec3& o, const Vec3& d, float tmin, float tmax, PCG32& rng,
           Stats& stats) const {
    stats.rays++;
    return Li_hit(scene, o, d, scene.intersect(o, d, tmin, tmax), rng, stats);
  }
  // Only the light reaching the camera through delta scattering (the extra
  // paths of Stats::split_delta); integrators that do not split return 0.
  virtual Color Li_delta(const Scene&, const Vec3&, const Vec3&, float, float, PCG32&, Stats&) const {
    return Color(0.f);
  }
  // Li_delta is a branched estimate (PathParams::delta_branch), far less noisy
  // than the delta part of a sample's own camera path (render.cpp then leaves
  // that part out of a split pixel's mean).
  virtual bool delta_branched() const { return false; }
  // The light tracer of the caustics the camera sees (point and spot lights,
  // area lights on request; integrators/light_trace.h), or null: each render
  // pass then also traces its photons.
  virtual const LightTracer* light_tracer() const { return nullptr; }
};

}  // namespace mpg
