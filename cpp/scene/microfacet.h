// GGX (Trowbridge-Reitz) and Beckmann microfacet distributions, anisotropic,
// with Smith masking. Walter et al. 2007 (EGSR) for the BSDF model; Heitz 2018
// (JCGT 7(4)) for GGX visible-normal sampling.
#pragma once

#include "core/math.h"

namespace mpg {

enum class MicrofacetType { Beckmann, GGX };

struct Microfacet {
  MicrofacetType type = MicrofacetType::Beckmann;
  float ax = 0.1f, ay = 0.1f;
  bool sample_visible = true;

  // Normal distribution D(m) (Walter 2007 Eqs. 25 and 33, anisotropic form).
  float D(const Vec3& m) const {
    if (m.z <= 0.f) return 0.f;
    const float x = m.x / ax, y = m.y / ay, z2 = m.z * m.z;
    float r;
    if (type == MicrofacetType::Beckmann) {
      r = std::exp(-(x * x + y * y) / z2) / (kPi * ax * ay * z2 * z2);
    } else {
      const float d = x * x + y * y + z2;
      r = 1.f / (kPi * ax * ay * d * d);
    }
    return (r * m.z > 1e-20f) ? r : 0.f;
  }

  // Smith G1 (Walter 2007 Eqs. 27 and 34; Beckmann with its rational approximation).
  float G1(const Vec3& v, const Vec3& m) const {
    if (glm::dot(v, m) * v.z <= 0.f) return 0.f;
    const float tan2 = (1.f - v.z * v.z) / (v.z * v.z);
    if (!(tan2 > 0.f)) return 1.f;
    const float alpha2 = (sqr(ax * v.x) + sqr(ay * v.y)) / std::max(1e-20f, 1.f - v.z * v.z);
    if (type == MicrofacetType::Beckmann) {
      const float a = 1.f / std::sqrt(alpha2 * tan2);
      if (a >= 1.6f) return 1.f;
      return (3.535f * a + 2.181f * a * a) / (1.f + 2.276f * a + 2.577f * a * a);
    }
    return 2.f / (1.f + std::sqrt(1.f + alpha2 * tan2));
  }
  float G(const Vec3& wi, const Vec3& wo, const Vec3& m) const { return G1(wi, m) * G1(wo, m); }

  // Sample a microfacet normal; returns m and its density (per solid angle of m).
  Vec3 sample(const Vec3& wi, const Vec2& u, float& pdf) const {
    if (sample_visible && type == MicrofacetType::GGX) {
      const Vec3 w = wi.z < 0.f ? -wi : wi;
      const Vec3 m = sample_visible_ggx(w, u);
      pdf = pdf_m(wi, m);
      return m;
    }
    return sample_dcos(u, pdf);
  }

  // Slope-space sampling of D(m) cos(theta_m) (independent of the incident direction).
  Vec3 sample_dcos(const Vec2& u, float& pdf) const {
    float sx, sy;
    const float phi = 2.f * kPi * u.y;
    if (type == MicrofacetType::Beckmann) {
      const float r = std::sqrt(-std::log(std::max(1.f - u.x, 1e-30f)));
      sx = r * std::cos(phi);
      sy = r * std::sin(phi);
    } else {
      const float r = std::sqrt(u.x / std::max(1.f - u.x, 1e-30f));
      sx = r * std::cos(phi);
      sy = r * std::sin(phi);
    }
    const Vec3 m = glm::normalize(Vec3(-sx * ax, -sy * ay, 1.f));
    pdf = D(m) * m.z;
    return m;
  }

  // Density of `sample` for the normal m given wi.
  float pdf_m(const Vec3& wi, const Vec3& m) const {
    if (sample_visible && type == MicrofacetType::GGX) {
      const Vec3 w = wi.z < 0.f ? -wi : wi;
      if (w.z <= 0.f) return 0.f;
      return G1(w, m) * std::abs(glm::dot(w, m)) * D(m) / w.z;
    }
    return D(m) * m.z;
  }

 private:
  Vec3 sample_visible_ggx(const Vec3& wi, const Vec2& u) const {
    const Vec3 vh = glm::normalize(Vec3(ax * wi.x, ay * wi.y, wi.z));
    const float lensq = vh.x * vh.x + vh.y * vh.y;
    const Vec3 t1 = lensq > 0.f ? Vec3(-vh.y, vh.x, 0.f) / std::sqrt(lensq) : Vec3(1.f, 0.f, 0.f);
    const Vec3 t2 = glm::cross(vh, t1);
    const float r = std::sqrt(u.x), phi = 2.f * kPi * u.y;
    const float p1 = r * std::cos(phi);
    float p2 = r * std::sin(phi);
    const float s = 0.5f * (1.f + vh.z);
    p2 = (1.f - s) * std::sqrt(std::max(0.f, 1.f - p1 * p1)) + s * p2;
    const Vec3 nh = p1 * t1 + p2 * t2 + safe_sqrt(1.f - p1 * p1 - p2 * p2) * vh;
    return glm::normalize(Vec3(ax * nh.x, ay * nh.y, std::max(1e-6f, nh.z)));
  }
};

}  // namespace mpg
