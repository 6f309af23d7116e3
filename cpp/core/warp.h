// Sample warps from [0,1)^2 with their densities. Densities are w.r.t. solid
// angle for directions and area for points.
#pragma once

#include "core/math.h"

namespace mpg {
namespace warp {

inline Vec3 square_to_uniform_sphere(const Vec2& u) {
  const float z = 1.f - 2.f * u.y;
  const float r = safe_sqrt(1.f - z * z);
  const float phi = 2.f * kPi * u.x;
  return Vec3(r * std::cos(phi), r * std::sin(phi), z);
}
inline float uniform_sphere_pdf() { return kInv4Pi; }

inline Vec3 square_to_uniform_hemisphere(const Vec2& u) {
  const float z = u.y;
  const float r = safe_sqrt(1.f - z * z);
  const float phi = 2.f * kPi * u.x;
  return Vec3(r * std::cos(phi), r * std::sin(phi), z);
}
inline float uniform_hemisphere_pdf(const Vec3& v) { return v.z >= 0.f ? kInv2Pi : 0.f; }

// Shirley-Chiu concentric map (low distortion).
inline Vec2 square_to_uniform_disk_concentric(const Vec2& u) {
  const float x = 2.f * u.x - 1.f, y = 2.f * u.y - 1.f;
  if (x == 0.f && y == 0.f) return Vec2(0.f);
  float r, phi;
  if (std::abs(x) > std::abs(y)) {
    r = x;
    phi = (kPi / 4.f) * (y / x);
  } else {
    r = y;
    phi = (kPi / 2.f) - (kPi / 4.f) * (x / y);
  }
  return Vec2(r * std::cos(phi), r * std::sin(phi));
}

inline Vec3 square_to_cosine_hemisphere(const Vec2& u) {
  const Vec2 d = square_to_uniform_disk_concentric(u);
  const float z = safe_sqrt(1.f - d.x * d.x - d.y * d.y);
  return Vec3(d.x, d.y, z);
}
inline float cosine_hemisphere_pdf(const Vec3& v) { return v.z > 0.f ? v.z * kInvPi : 0.f; }

// Uniform in a cone of directions around +z with cos(theta) >= cos_max.
inline Vec3 square_to_uniform_cone(const Vec2& u, float cos_max) {
  const float z = 1.f - u.y * (1.f - cos_max);
  const float r = safe_sqrt(1.f - z * z);
  const float phi = 2.f * kPi * u.x;
  return Vec3(r * std::cos(phi), r * std::sin(phi), z);
}
inline float uniform_cone_pdf(const Vec3& v, float cos_max) {
  return v.z >= cos_max ? 1.f / (2.f * kPi * (1.f - cos_max)) : 0.f;
}

// Barycentrics (b1, b2) uniform on a triangle (Heitz 2019, low-distortion map).
inline Vec2 square_to_uniform_triangle(const Vec2& u) {
  float b0, b1;
  if (u.x < u.y) {
    b0 = u.x / 2.f;
    b1 = u.y - b0;
  } else {
    b1 = u.y / 2.f;
    b0 = u.x - b1;
  }
  return Vec2(b0, b1);
}

// von Mises-Fisher distribution around +z with concentration kappa.
// Density (MPG supplemental Eq. 1): v(w) = kappa / (4 pi sinh kappa) exp(kappa cos).
// Written as kappa / (2 pi (1 - e^{-2 kappa})) exp(kappa (cos - 1)) so that it
// neither overflows for kappa = 1e8 nor cancels for kappa = 1e-8.
// The factor kappa / (2 pi (1 - e^{-2 kappa})) (kappa > 1e-12). Above kappa =
// 20, 1 - e^{-40} is 1 in double, so the expm1 is skipped: the same bits.
inline double vmf_norm(double kappa) {
  const double den = kappa > 20.0 ? 1.0 : -std::expm1(-2.0 * kappa);
  return kappa / (2.0 * 3.14159265358979323846 * den);
}
inline double vmf_pdf_cos(double cos_theta, double kappa) {
  if (!(kappa > 1e-12)) return 1.0 / (4.0 * 3.14159265358979323846);
  return vmf_norm(kappa) * std::exp(kappa * (std::min(cos_theta, 1.0) - 1.0));
}
inline float vmf_pdf(const Vec3& v, float kappa) { return float(vmf_pdf_cos(v.z, kappa)); }

// Sampling by inversion (MPG supplemental Eqs. 2-3, Jakob 2012):
// W = log(e^{-kappa} + 2 xi sinh kappa) / kappa, rewritten as
// W = 1 + log1p((1 - xi) * expm1(-2 kappa)) / kappa  (xi -> 1 - xi is the same law).
inline Vec3 square_to_vmf(const Vec2& u, float kappa) {
  double w;
  const double k = kappa;
  if (!(k > 1e-12)) {
    w = 1.0 - 2.0 * double(u.y);
  } else {
    w = 1.0 + std::log1p(double(u.y) * std::expm1(-2.0 * k)) / k;
  }
  w = std::clamp(w, -1.0, 1.0);
  const double r = std::sqrt(std::max(0.0, (1.0 - w) * (1.0 + w)));
  const double phi = 2.0 * 3.14159265358979323846 * double(u.x);
  return Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(w));
}

}  // namespace warp
}  // namespace mpg
