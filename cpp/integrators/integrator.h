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
  // ... and, with glints on, the glints' estimate from the same ray and first
  // hit (after the path, so the path's random numbers stay as without them;
  // stats.sample_glint holds it). Stats::film_x/film_y: the ray's pixel.
  Color Li(const Scene& scene, const Vec3& o, const Vec3& d, float tmin, float tmax, PCG32& rng,
           Stats& stats) const {
    stats.rays++;
    stats.sample_glint = Color(0.f);
    if (!glints_on()) return Li_hit(scene, o, d, scene.intersect(o, d, tmin, tmax), rng, stats);
    const SurfaceInteraction si = scene.intersect(o, d, tmin, tmax);
    Color L = Li_hit(scene, o, d, si, rng, stats);
    stats.sample_glint = glint(o, d, si, rng, stats);
    return L + stats.sample_glint;
  }
  // The glints (ChainEstimator::glint): whether they run, and one estimate.
  virtual bool glints_on() const { return false; }
  virtual Color glint(const Vec3&, const Vec3&, const SurfaceInteraction&, PCG32&, Stats&) const {
    return Color(0.f);
  }
  // Only the light reaching the camera through delta scattering (the extra
  // paths of Stats::split_delta); integrators that do not split return 0.
  // branch: a branched estimate where the integrator branches (delta_branched);
  // false: the plain Only path (the pixel's learned choice, render.cpp).
  virtual Color Li_delta(const Scene&, const Vec3&, const Vec3&, float, float, PCG32&, Stats&,
                         bool /*branch*/) const {
    return Color(0.f);
  }
  // Li_delta is a branched estimate (PathParams::delta_branch), far less noisy
  // than the delta part of a sample's own camera path (render.cpp then leaves
  // that part out of a split pixel's mean).
  virtual bool delta_branched() const { return false; }
  // The delta split's extra paths take their film positions from a per-pixel
  // Sobol sequence (PathParams::delta_split_sobol), not independent ones.
  virtual bool delta_split_sobol() const { return false; }
  // The light tracer of the caustics the camera sees (point and spot lights,
  // area lights on request; integrators/light_trace.h), or null: each render
  // pass then also traces its photons.
  virtual const LightTracer* light_tracer() const { return nullptr; }
};

}  // namespace mpg
