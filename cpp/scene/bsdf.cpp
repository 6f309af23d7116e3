#include "scene/bsdf.h"

#include "core/warp.h"
#include "scene/fresnel.h"

namespace mpg {

float fresnel_diffuse_reflectance(float eta) {
  // 2 * integral_0^1 F(mu, eta) mu dmu, midpoint rule on 4096 intervals
  // (F varies smoothly except at the critical angle; error < 1e-5).
  const int n = 4096;
  double s = 0.0;
  for (int i = 0; i < n; ++i) {
    const double mu = (i + 0.5) / n;
    s += double(fresnel_dielectric(float(mu), eta).F) * mu;
  }
  return float(2.0 * s / n);
}

namespace {
inline float sign_of(float x) { return x < 0.f ? -1.f : 1.f; }
}  // namespace

bool BSDFSet::uses_uv(int id) const {
  if (id < 0 || id >= int(nodes.size())) return false;
  const BSDF& b = nodes[size_t(id)];
  for (int t : {b.reflectance, b.specular_reflectance, b.specular_transmittance, b.normalmap})
    if (t >= 0 && textures[size_t(t)].kind != Texture::Kind::Constant) return true;
  for (int c : {b.front, b.back, b.nested})
    if (c >= 0 && c != id && uses_uv(c)) return true;
  return false;
}

BSDFContext BSDFSet::resolve(int id, const SurfaceInteraction& si) const {
  BSDFContext c;
  c.frame = si.sh;
  c.base = si.sh;
  c.uv = si.uv;
  for (int guard = 0; guard < 16 && id >= 0; ++guard) {
    const BSDF& b = nodes[size_t(id)];
    if (b.type == BSDFType::TwoSided) {
      if (glm::dot(si.wi, c.frame.n) < 0.f) {
        c.frame = Frame(c.frame.s, c.frame.t, -c.frame.n);  // mirror z, as Mitsuba 3's twosided
        c.base = Frame(c.base.s, c.base.t, -c.base.n);
        id = b.back;
      } else {
        id = b.front;
      }
      continue;
    }
    if (b.type == BSDFType::NormalMap) {
      // Tangent-space normal: components along (s, t, n) of the shading frame.
      const Color t = tex(b.normalmap, si.uv, 0.5f);
      Vec3 nl = 2.f * Vec3(t) - 1.f;
      if (!(glm::dot(nl, nl) > 1e-12f) || !is_finite(nl)) nl = Vec3(0.f, 0.f, 1.f);
      const Vec3 n = glm::normalize(c.frame.to_world(nl));
      c.base = c.frame;
      c.frame = Frame::from_normal_tangent(n, c.frame.s);
      c.perturbed = true;
      id = b.nested;
      continue;
    }
    c.leaf = &b;
    return c;
  }
  c.leaf = nullptr;
  return c;
}

Color BSDFSet::eval(const BSDFContext& c, const Vec3& wi, const Vec3& wo) const {
  if (!c.leaf) return Color(0.f);
  const Vec3 wo_l = c.frame.to_local(wo);
  if (c.perturbed && c.base.to_local(wo).z * wo_l.z <= 0.f) return Color(0.f);
  return eval_local(*c.leaf, c.uv, c.frame.to_local(wi), wo_l);
}

float BSDFSet::pdf(const BSDFContext& c, const Vec3& wi, const Vec3& wo) const {
  if (!c.leaf) return 0.f;
  const Vec3 wo_l = c.frame.to_local(wo);
  if (c.perturbed && c.base.to_local(wo).z * wo_l.z <= 0.f) return 0.f;
  return pdf_local(*c.leaf, c.uv, c.frame.to_local(wi), wo_l);
}

BSDFSample BSDFSet::sample(const BSDFContext& c, const Vec3& wi, float u1, const Vec2& u2,
                           Vec3& wo_world) const {
  BSDFSample s;
  if (!c.leaf) return s;
  s = sample_local(*c.leaf, c.uv, c.frame.to_local(wi), u1, u2);
  if (s.pdf <= 0.f) return s;
  wo_world = c.frame.to_world(s.wo);
  if (c.perturbed && !s.null && c.base.to_local(wo_world).z * s.wo.z <= 0.f) {
    s.pdf = 0.f;
    s.weight = Color(0.f);
  }
  return s;
}

// ---------------------------------------------------------------------------
// Leaf BSDFs in local coordinates.

Color BSDFSet::eval_local(const BSDF& b, const Vec2& uv, const Vec3& wi, const Vec3& wo) const {
  const float ci = wi.z, co = wo.z;
  switch (b.type) {
    case BSDFType::Diffuse:
      if (ci <= 0.f || co <= 0.f) return Color(0.f);
      return tex(b.reflectance, uv, 0.5f) * (kInvPi * co);
    case BSDFType::RoughConductor: {
      if (ci <= 0.f || co <= 0.f) return Color(0.f);
      const Vec3 h = glm::normalize(wi + wo);
      const float D = b.mf.D(h);
      if (D == 0.f) return Color(0.f);
      const float G = b.mf.G(wi, wo, h);
      const Color F = fresnel_conductor(glm::dot(wi, h), b.eta_c, b.k_c);
      // Walter 2007 Eq. 20: f = F D G / (4 |cos_i| |cos_o|), times cos_o.
      return tex(b.specular_reflectance, uv) * F * (D * G / (4.f * ci));
    }
    case BSDFType::RoughDielectric: {
      if (ci == 0.f || co == 0.f) return Color(0.f);
      const bool refl = ci * co > 0.f;
      const float eta_p = ci > 0.f ? b.eta : 1.f / b.eta;
      Vec3 m = refl ? (wi + wo) : (wi + wo * eta_p);
      const float ml = glm::length(m);
      if (!(ml > 0.f)) return Color(0.f);
      m = m * (sign_of(m.z) / ml);
      const float D = b.mf.D(m);
      if (D == 0.f) return Color(0.f);
      const float G = b.mf.G(wi, wo, m);
      const float F = fresnel_dielectric(glm::dot(wi, m), b.eta).F;
      if (refl) return tex(b.specular_reflectance, uv) * (F * D * G / (4.f * std::abs(ci)));
      const float wim = glm::dot(wi, m), wom = glm::dot(wo, m);
      const float denom = wim + eta_p * wom;
      if (wim * wom >= 0.f || denom == 0.f) return Color(0.f);
      // Walter 2007 Eq. 21; the eta_p^2 of the Jacobian cancels the 1/eta_p^2
      // radiance scaling of camera paths (Veach 1997, Sec. 5.2).
      const float v = (1.f - F) * D * G * std::abs(wim * wom) / (std::abs(ci) * denom * denom);
      return tex(b.specular_transmittance, uv) * v;
    }
    case BSDFType::Plastic: {
      if (ci <= 0.f || co <= 0.f) return Color(0.f);
      const float Fi = fresnel_dielectric(ci, b.eta).F, Fo = fresnel_dielectric(co, b.eta).F;
      Color diff = tex(b.reflectance, uv, 0.5f);
      diff = diff / (1.f - (b.nonlinear ? diff * b.fdr_int : Color(b.fdr_int)));
      return diff * (kInvPi * co * (1.f - Fi) * (1.f - Fo) / (b.eta * b.eta));
    }
    default:
      return Color(0.f);  // delta and null BSDFs have no density
  }
}

float BSDFSet::pdf_local(const BSDF& b, const Vec2& uv, const Vec3& wi, const Vec3& wo) const {
  const float ci = wi.z, co = wo.z;
  switch (b.type) {
    case BSDFType::Diffuse:
      if (ci <= 0.f || co <= 0.f) return 0.f;
      return warp::cosine_hemisphere_pdf(wo);
    case BSDFType::RoughConductor: {
      if (ci <= 0.f || co <= 0.f) return 0.f;
      const Vec3 h = glm::normalize(wi + wo);
      return b.mf.pdf_m(wi, h) / (4.f * glm::dot(wo, h));
    }
    case BSDFType::RoughDielectric: {
      if (ci == 0.f || co == 0.f) return 0.f;
      const bool refl = ci * co > 0.f;
      const float eta_p = ci > 0.f ? b.eta : 1.f / b.eta;
      Vec3 m = refl ? (wi + wo) : (wi + wo * eta_p);
      const float ml = glm::length(m);
      if (!(ml > 0.f)) return 0.f;
      m = m * (sign_of(m.z) / ml);
      const float wim = glm::dot(wi, m), wom = glm::dot(wo, m);
      // Both directions must be on the sides the microfacet normal implies.
      if (wim * ci <= 0.f || wom * co <= 0.f) return 0.f;
      const float F = fresnel_dielectric(wim, b.eta).F;
      const float pm = b.mf.pdf_m(wi * sign_of(ci), m);
      if (refl) return pm * F / (4.f * std::abs(wom));
      const float denom = wim + eta_p * wom;
      if (denom == 0.f) return 0.f;
      return pm * (1.f - F) * eta_p * eta_p * std::abs(wom) / (denom * denom);
    }
    case BSDFType::Plastic: {
      if (ci <= 0.f || co <= 0.f) return 0.f;
      const float Fi = fresnel_dielectric(ci, b.eta).F;
      const float ps = Fi * b.specular_sampling_weight;
      const float pd = (1.f - Fi) * (1.f - b.specular_sampling_weight);
      return (pd / (ps + pd)) * warp::cosine_hemisphere_pdf(wo);
    }
    default:
      return 0.f;
  }
}

BSDFSample BSDFSet::sample_local(const BSDF& b, const Vec2& uv, const Vec3& wi, float u1,
                                 const Vec2& u2) const {
  BSDFSample s;
  const float ci = wi.z;
  switch (b.type) {
    case BSDFType::Null:
      s.wo = -wi;
      s.weight = Color(1.f);
      s.pdf = 1.f;
      s.delta = s.null = s.transmission = true;
      return s;
    case BSDFType::Diffuse: {
      if (ci <= 0.f) return s;
      s.wo = warp::square_to_cosine_hemisphere(u2);
      s.pdf = warp::cosine_hemisphere_pdf(s.wo);
      if (s.pdf <= 0.f) return s;
      s.weight = tex(b.reflectance, uv, 0.5f);
      return s;
    }
    case BSDFType::Conductor: {
      if (ci <= 0.f) return s;
      s.wo = reflect_local(wi);
      s.pdf = 1.f;
      s.delta = true;
      s.weight = tex(b.specular_reflectance, uv) * fresnel_conductor(ci, b.eta_c, b.k_c);
      return s;
    }
    case BSDFType::Dielectric: {
      const DielectricFresnel f = fresnel_dielectric(ci, b.eta);
      s.delta = true;
      if (u1 <= f.F) {
        s.wo = reflect_local(wi);
        s.pdf = f.F;
        s.weight = tex(b.specular_reflectance, uv);
      } else {
        s.wo = refract_local(wi, f);
        s.pdf = 1.f - f.F;
        s.eta = f.eta_it;
        s.transmission = true;
        // Radiance is scaled by (eta_i / eta_t)^2 when crossing (Veach 1997, Sec. 5.2).
        s.weight = tex(b.specular_transmittance, uv) * (f.eta_ti * f.eta_ti);
      }
      return s;
    }
    case BSDFType::ThinDielectric: {
      float r = fresnel_dielectric(std::abs(ci), b.eta).F;
      // Infinite series of internal reflections in a thin sheet: R' = R + T^2 R / (1 - R^2).
      if (r < 1.f) r += sqr(1.f - r) * r / (1.f - r * r);
      s.delta = true;
      if (u1 <= r) {
        s.wo = reflect_local(wi);
        s.pdf = r;
        s.weight = tex(b.specular_reflectance, uv);
      } else {
        s.wo = -wi;
        s.pdf = 1.f - r;
        s.transmission = true;
        s.weight = tex(b.specular_transmittance, uv);
      }
      return s;
    }
    case BSDFType::Plastic: {
      if (ci <= 0.f) return s;
      const float Fi = fresnel_dielectric(ci, b.eta).F;
      float ps = Fi * b.specular_sampling_weight;
      float pd = (1.f - Fi) * (1.f - b.specular_sampling_weight);
      ps = ps / (ps + pd);
      pd = 1.f - ps;
      if (u1 < ps) {
        s.wo = reflect_local(wi);
        s.pdf = ps;
        s.delta = true;
        s.weight = tex(b.specular_reflectance, uv) * (Fi / ps);
      } else {
        s.wo = warp::square_to_cosine_hemisphere(u2);
        s.pdf = pd * warp::cosine_hemisphere_pdf(s.wo);
        if (s.pdf <= 0.f) { s.pdf = 0.f; return s; }
        s.weight = eval_local(b, uv, wi, s.wo) / s.pdf;
      }
      return s;
    }
    case BSDFType::RoughConductor: {
      if (ci <= 0.f) return s;
      float pm;
      const Vec3 m = b.mf.sample(wi, u2, pm);
      if (!(pm > 0.f)) return s;
      s.wo = reflect(wi, m);
      if (s.wo.z <= 0.f) return s;
      s.pdf = pdf_local(b, uv, wi, s.wo);
      if (!(s.pdf > 0.f)) { s.pdf = 0.f; return s; }
      s.weight = eval_local(b, uv, wi, s.wo) / s.pdf;
      return s;
    }
    case BSDFType::RoughDielectric: {
      if (ci == 0.f) return s;
      if (b.eta == 1.f) {
        // Index-matched: F = 0 and every microfacet refracts wi to -wi, so the
        // BTDF is a delta (eval/pdf are 0: the generalised half vector of
        // Walter 2007 Eq. 16 degenerates). As pbrt-v4's DielectricBxDF
        // (eta == 1 -> specular), pass straight through instead of rejecting
        // every sample, which made the interface absorb all light.
        s.wo = -wi;
        s.pdf = 1.f;
        s.delta = s.transmission = true;
        s.weight = tex(b.specular_transmittance, uv);
        return s;
      }
      float pm;
      const Vec3 m = b.mf.sample(wi * sign_of(ci), u2, pm);
      if (!(pm > 0.f)) return s;
      const float wim = glm::dot(wi, m);
      // A normal facing away from wi (possible when sampling D(m) cos(theta_m)
      // rather than visible normals) has G1(wi, m) = 0: Walter 2007 Eq. 7's
      // chi+(v.m / v.n). Refracting through it used the wrong Fresnel side and
      // landed on a wo whose generalised half vector is another, front-facing
      // m', weighted eval/pdf as if drawn through m': extra energy. pdf_local
      // gives such m no density, so the sample is rejected (weight 0).
      if (wim * ci <= 0.f) return s;
      const DielectricFresnel f = fresnel_dielectric(wim, b.eta);
      if (u1 <= f.F) {
        s.wo = reflect(wi, m);
        if (s.wo.z * ci <= 0.f) return s;
      } else {
        s.wo = refract(wi, m, f.cos_t, f.eta_ti);
        if (s.wo.z * ci >= 0.f) return s;
        s.transmission = true;
        s.eta = f.eta_it;
      }
      s.pdf = pdf_local(b, uv, wi, s.wo);
      if (!(s.pdf > 0.f)) { s.pdf = 0.f; return s; }
      s.weight = eval_local(b, uv, wi, s.wo) / s.pdf;
      return s;
    }
    default:
      return s;
  }
}

}  // namespace mpg
