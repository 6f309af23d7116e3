// Shapes: triangle meshes (vertex normals and UVs optional) and exact spheres.
#pragma once

#include <vector>

#include "core/distribution.h"
#include "core/math.h"

namespace mpg {

struct Shape {
  enum class Kind { Mesh, Sphere };
  Kind kind = Kind::Mesh;
  std::vector<Vec3> positions, normals;
  std::vector<Vec2> uvs;
  std::vector<glm::uvec3> indices;
  Vec3 center{0.f};
  float radius = 1.f;
  int bsdf = -1;
  int emitter = -1;
  bool flip_normals = false;
  // The scene marks it caustic_receiver: never a chain vertex when glossy (the
  // chain estimators' x_D side; a smooth one stays one; ChainEstimator).
  bool caustic_receiver = false;
  bool needs_uv = true;           // false when the BSDF uses no spatially varying texture
  float area = 0.f;
  DiscreteDistribution tri_dist;  // by triangle area

  // Grow the box [lo, hi] by the shape's bounds.
  void grow_bounds(Vec3& lo, Vec3& hi) const {
    if (kind == Kind::Sphere) {
      lo = glm::min(lo, center - Vec3(radius));
      hi = glm::max(hi, center + Vec3(radius));
      return;
    }
    for (const Vec3& q : positions) {
      lo = glm::min(lo, q);
      hi = glm::max(hi, q);
    }
  }

  void finalize() {
    if (kind == Kind::Sphere) {
      area = 4.f * kPi * radius * radius;
      return;
    }
    std::vector<float> a(indices.size());
    double total = 0.0;
    for (size_t i = 0; i < indices.size(); ++i) {
      a[i] = triangle_area(i);
      total += a[i];
    }
    area = float(total);
    tri_dist.build(a);
  }

  float triangle_area(size_t i) const {
    const glm::uvec3 t = indices[i];
    return 0.5f * glm::length(glm::cross(positions[t.y] - positions[t.x], positions[t.z] - positions[t.x]));
  }

  // Uniform point by area: position, geometric normal; density 1 / area.
  void sample_position(Vec2 u, Vec3& p, Vec3& n) const {
    if (kind == Kind::Sphere) {
      const float z = 1.f - 2.f * u.y, r = safe_sqrt(1.f - z * z), phi = 2.f * kPi * u.x;
      n = Vec3(r * std::cos(phi), r * std::sin(phi), z);
      p = center + radius * n;
      if (flip_normals) n = -n;
      return;
    }
    float ux = u.x;
    const size_t i = tri_dist.sample(ux);
    const glm::uvec3 t = indices[i];
    float b1, b2;
    if (ux < u.y) { b1 = ux / 2.f; b2 = u.y - b1; } else { b2 = u.y / 2.f; b1 = ux - b2; }
    const Vec3 p0 = positions[t.x], p1 = positions[t.y], p2 = positions[t.z];
    p = p0 * (1.f - b1 - b2) + p1 * b1 + p2 * b2;
    n = glm::normalize(glm::cross(p1 - p0, p2 - p0));
    if (flip_normals) n = -n;
  }
};

}  // namespace mpg
