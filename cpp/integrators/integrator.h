// Integrator interface: radiance along one camera ray.
#pragma once

#include "core/rng.h"
#include "render/stats.h"
#include "scene/scene.h"

namespace mpg {

class Integrator {
 public:
  virtual ~Integrator() = default;
  virtual Color Li(const Scene& scene, const Vec3& o, const Vec3& d, float tmin, float tmax,
                   PCG32& rng, Stats& stats) const = 0;
};

}  // namespace mpg
