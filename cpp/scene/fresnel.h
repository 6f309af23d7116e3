// Exact Fresnel equations for dielectrics and conductors.
#pragma once

#include "core/math.h"

namespace mpg {

struct DielectricFresnel {
  float F;       // reflectance
  float cos_t;   // cosine of the refracted direction (sign: opposite side of cos_i)
  float eta_it;  // relative IOR eta_t / eta_i along the direction of travel
  float eta_ti;  // 1 / eta_it
};

// eta = eta_int / eta_ext; cos_i > 0 means the incident direction is outside.
// Unpolarised exact Fresnel (e.g. Born & Wolf, Ch. 1.5; pbrt-v4 Eq. 9.4-9.5).
inline DielectricFresnel fresnel_dielectric(float cos_i, float eta) {
  const bool outside = cos_i >= 0.f;
  const float eta_it = outside ? eta : 1.f / eta;
  const float eta_ti = 1.f / eta_it;
  const float ci = std::min(std::abs(cos_i), 1.f);
  // Index-matched: no reflection at any angle, wo = -wi. Tested before the TIR
  // branch, where 1 - ci^2 rounds to 1 for ci < 2.4e-4 and gave F = 1 at
  // grazing incidence (as Mitsuba 3's fresnel(): r = 0, cos_t = -cos_i).
  if (eta == 1.f) return {0.f, outside ? -ci : ci, 1.f, 1.f};
  const float sin2_t = eta_ti * eta_ti * (1.f - ci * ci);
  if (sin2_t >= 1.f) return {1.f, 0.f, eta_it, eta_ti};  // total internal reflection
  const float ct = safe_sqrt(1.f - sin2_t);
  const float rs = (ci - eta_it * ct) / (ci + eta_it * ct);
  const float rp = (eta_it * ci - ct) / (eta_it * ci + ct);
  float F = 0.5f * (rs * rs + rp * rp);
  return {F, outside ? -ct : ct, eta_it, eta_ti};
}

// Refract local direction w (pointing away from the surface) given the Fresnel
// record; the result points away on the other side.
inline Vec3 refract_local(const Vec3& w, const DielectricFresnel& f) {
  return Vec3(-f.eta_ti * w.x, -f.eta_ti * w.y, f.cos_t);
}
// World-space refraction about normal m (w and m on the same side or not).
inline Vec3 refract(const Vec3& w, const Vec3& m, float cos_t, float eta_ti) {
  const float c = glm::dot(w, m);
  return m * (c * eta_ti + cos_t) - w * eta_ti;
}

// Conductor Fresnel with complex IOR eta + i k (from a medium of index 1),
// per channel: the unpolarised reflectance 0.5 (R_s + R_p) of Born & Wolf
// Sec. 14.2 (pbrt-v4 Eq. 9.6) written in real arithmetic with
// a^2 + b^2 = |eta^2 - k^2 - sin^2 + 2 i eta k| and a = Re of the complex
// cos_t times eta (the form of pbrt-v3 Sec. 8.2.1). The same values as the
// complex form (tests/test_bsdfs.py against it in float64) at a fraction of
// its cost: std::sqrt of a complex float called csqrtf and hypotf, and the
// divisions were complex. On the plane (rough conductor floor and panel) the
// path tracer takes 0.80x the time it took, on the ring 0.92x
// (bench/ab_core.sh, 256 spp, docs/benchmarks.md). In double: a^2 comes from
// a difference that cancels when k >> eta, taken there as the equal quotient
// 2 eta^2 k^2 / (a^2 + b^2 - t0).
inline float fresnel_conductor_1(float cos_i, float eta, float k) {
  const double c = std::clamp(double(cos_i), 0.0, 1.0);
  const double c2 = c * c, s2 = 1.0 - c2;
  const double e2 = double(eta) * eta, k2 = double(k) * k;
  const double t0 = e2 - k2 - s2;
  const double ab = std::sqrt(t0 * t0 + 4.0 * e2 * k2);          // a^2 + b^2
  const double a2 = t0 >= 0.0 ? 0.5 * (ab + t0) : (ab - t0 > 0.0 ? 2.0 * e2 * k2 / (ab - t0) : 0.0);
  const double a = std::sqrt(std::max(a2, 0.0));
  const double t1 = ab + c2, t2 = 2.0 * c * a;
  const double rs = (t1 - t2) / (t1 + t2);
  const double t3 = c2 * ab + s2 * s2, t4 = t2 * s2;
  const double rp = rs * (t3 - t4) / (t3 + t4);
  const double F = 0.5 * (rs + rp);
  return std::isfinite(F) ? float(std::clamp(F, 0.0, 1.0)) : 1.f;
}
inline Color fresnel_conductor(float cos_i, const Color& eta, const Color& k) {
  return Color(fresnel_conductor_1(cos_i, eta.x, k.x), fresnel_conductor_1(cos_i, eta.y, k.y),
               fresnel_conductor_1(cos_i, eta.z, k.z));
}

// Hemispherical average of the dielectric Fresnel reflectance,
// 2 * integral_0^1 F(mu) mu dmu, by Gauss-Legendre quadrature (used by plastic).
float fresnel_diffuse_reflectance(float eta);

}  // namespace mpg
