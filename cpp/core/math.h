// Small math layer on GLM: vectors, frames, numerically careful helpers.
#pragma once

#include <glm/glm.hpp>
#include <glm/gtc/matrix_transform.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace mpg {

using Vec2 = glm::vec2;
using Vec3 = glm::vec3;
using Vec4 = glm::vec4;
using Mat3 = glm::mat3;
using Mat4 = glm::mat4;
using Color = glm::vec3;  // linear RGB

constexpr float kPi = 3.14159265358979323846f;
constexpr float kInvPi = 0.31830988618379067154f;
constexpr float kInv2Pi = 0.15915494309189533577f;
constexpr float kInv4Pi = 0.07957747154594766788f;
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kOneMinusEps = 0x1.fffffep-1f;

inline float sqr(float x) { return x * x; }
inline float safe_sqrt(float x) { return std::sqrt(std::max(x, 0.f)); }
inline float safe_acos(float x) { return std::acos(std::clamp(x, -1.f, 1.f)); }
inline float safe_asin(float x) { return std::asin(std::clamp(x, -1.f, 1.f)); }
inline float max_comp(const Vec3& v) { return std::max(v.x, std::max(v.y, v.z)); }
inline float mean(const Color& c) { return (c.x + c.y + c.z) * (1.f / 3.f); }
inline float luminance(const Color& c) { return 0.212671f * c.x + 0.715160f * c.y + 0.072169f * c.z; }
inline bool is_finite(const Vec3& v) {
  return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}
inline bool is_black(const Color& c) { return c.x == 0.f && c.y == 0.f && c.z == 0.f; }
// Mean over RGB of the square, in double (as the pixel statistics take it)
inline double mean_square(const Color& c) {
  return (double(c.x) * c.x + double(c.y) * c.y + double(c.z) * c.z) / 3.0;
}

// Build an orthonormal basis from a unit vector (Duff et al. 2017, "Building an
// Orthonormal Basis, Revisited", Listing 3).
inline void coordinate_system(const Vec3& n, Vec3& s, Vec3& t) {
  const float sign = std::copysign(1.f, n.z);
  const float a = -1.f / (sign + n.z);
  const float b = n.x * n.y * a;
  s = Vec3(1.f + sign * n.x * n.x * a, sign * b, -sign * n.x);
  t = Vec3(b, sign + n.y * n.y * a, -n.y);
}

// Orthonormal frame (s, t, n); local z is the normal.
struct Frame {
  Vec3 s{1, 0, 0}, t{0, 1, 0}, n{0, 0, 1};
  Frame() = default;
  explicit Frame(const Vec3& normal) : n(normal) { coordinate_system(n, s, t); }
  Frame(const Vec3& s_, const Vec3& t_, const Vec3& n_) : s(s_), t(t_), n(n_) {}
  // Frame whose s axis follows a tangent (Gram-Schmidt); falls back to any basis.
  static Frame from_normal_tangent(const Vec3& n, const Vec3& tangent) {
    Vec3 s = tangent - n * glm::dot(n, tangent);
    const float l2 = glm::dot(s, s);
    if (!(l2 > 1e-20f)) return Frame(n);
    s *= 1.f / std::sqrt(l2);
    return Frame(s, glm::cross(n, s), n);
  }
  Vec3 to_local(const Vec3& v) const { return Vec3(glm::dot(v, s), glm::dot(v, t), glm::dot(v, n)); }
  Vec3 to_world(const Vec3& v) const { return s * v.x + t * v.y + n * v.z; }
  Frame flipped() const { return Frame(s, -t, -n); }
};

inline float cos_theta(const Vec3& w) { return w.z; }
inline float abs_cos_theta(const Vec3& w) { return std::abs(w.z); }

inline Vec3 reflect_local(const Vec3& w) { return Vec3(-w.x, -w.y, w.z); }
inline Vec3 reflect(const Vec3& w, const Vec3& m) { return 2.f * glm::dot(w, m) * m - w; }

// Offset a ray origin along the geometric normal to escape self-intersection.
inline Vec3 offset_ray_origin(const Vec3& p, const Vec3& ng, const Vec3& dir) {
  const float scale = 1e-4f * std::max(1.f, max_comp(glm::abs(p)));
  return p + ng * (glm::dot(dir, ng) >= 0.f ? scale : -scale);
}

inline float power_heuristic(float a, float b) {
  const float a2 = a * a, b2 = b * b;
  if (!(a2 + b2 > 0.f)) return 0.f;
  if (std::isinf(a2)) return 1.f;
  return a2 / (a2 + b2);
}

}  // namespace mpg
