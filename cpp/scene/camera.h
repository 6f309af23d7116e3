// Perspective camera (Mitsuba 3 conventions: local +z forward, +y up, +x left)
// and pixel reconstruction filters sampled by importance (one unbiased estimate
// per sample, so pixels stay independent).
#pragma once

#include <vector>

#include "core/math.h"

namespace mpg {

struct FilterSampler {
  enum class Type { Box, Gaussian, Tent };
  Type type = Type::Box;
  float radius = 0.5f;
  std::vector<float> cdf;  // tabulated 1D CDF over [-radius, radius]

  // Build from the 1D filter profile w(x) (separable filters).
  void build(Type t, float stddev, float tent_radius);
  // Offset from the pixel centre, one axis.
  float sample(float u) const;
};

struct Camera {
  Mat4 to_world{1.f};
  float tan_half_x = 0.4142f, tan_half_y = 0.4142f;
  float near_clip = 1e-2f, far_clip = 1e4f;
  int width = 256, height = 256;
  int crop_x = 0, crop_y = 0, crop_w = 256, crop_h = 256;
  FilterSampler filter;

  // Film position in pixels of the full film (x right, y down).
  void generate_ray(const Vec2& film, Vec3& o, Vec3& d, float& tmin, float& tmax) const {
    const float sx = film.x / float(width), sy = film.y / float(height);
    const Vec3 local(-(2.f * sx - 1.f) * tan_half_x, -(2.f * sy - 1.f) * tan_half_y, 1.f);
    const Vec3 dl = glm::normalize(local);
    o = Vec3(to_world * Vec4(0.f, 0.f, 0.f, 1.f));
    const Vec3 dw = Vec3(to_world * Vec4(dl, 0.f));
    const float len = glm::length(dw);
    d = dw / len;
    // near/far clip are distances along the optical axis (Mitsuba 3).
    tmin = near_clip / dl.z * len;
    tmax = far_clip / dl.z * len;
  }
  // generate_ray inverted: the film position (pixels of the full film) of a
  // point q in the camera's local frame (inverse of to_world applied); false
  // behind the pinhole.
  bool film_position(const Vec4& q, Vec2& film) const {
    if (!(q.z > 0.f)) return false;
    const float X = q.x / q.z, Y = q.y / q.z;
    film = Vec2(0.5f * (1.f - X / tan_half_x) * float(width), 0.5f * (1.f - Y / tan_half_y) * float(height));
    return true;
  }
};

}  // namespace mpg
