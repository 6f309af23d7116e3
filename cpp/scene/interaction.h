// Surface interaction record filled by Scene::intersect.
#pragma once

#include "core/math.h"

namespace mpg {

struct SurfaceInteraction {
  bool valid = false;
  float t = kInf;
  Vec3 p{0.f};
  Vec3 ng{0.f, 0.f, 1.f};  // geometric normal (flip_normals applied)
  Frame sh;                // shading frame (interpolated normal, s along dp/du)
  Vec2 uv{0.f};
  Vec2 bary{0.f};          // triangle barycentrics (b1, b2) of the hit (meshes)
  Vec3 dpdu{1.f, 0.f, 0.f}, dpdv{0.f, 1.f, 0.f};
  Vec3 wi{0.f};            // world direction toward the previous vertex
  int shape = -1;
  int prim = -1;
};

}  // namespace mpg
