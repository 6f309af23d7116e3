#include "manifold/walk.h"

#include <cmath>

#include "manifold/dual.h"
#include "scene/fresnel.h"

namespace mpg {

const char* walk_failure_name(WalkFailure f) {
  switch (f) {
    case WalkFailure::None: return "none";
    case WalkFailure::SingularJacobian: return "singular_jacobian";
    case WalkFailure::TotalInternalReflection: return "total_internal_reflection";
    case WalkFailure::VanishingSegment: return "vanishing_segment";
    case WalkFailure::Stuck: return "stuck";
    case WalkFailure::LeftSurface: return "left_surface";
    case WalkFailure::StepTooSmall: return "step_too_small";
    case WalkFailure::MaxIterations: return "max_iterations";
    case WalkFailure::WrongHemisphere: return "wrong_hemisphere";
    case WalkFailure::Occluded: return "occluded";
    case WalkFailure::NotSpecular: return "not_specular";
    default: return "unknown";
  }
}

namespace {

constexpr double kPiD = 3.14159265358979323846;

DVec3 to_d(const Vec3& v) { return DVec3(v.x, v.y, v.z); }
Vec3 to_f(const DVec3& v) { return Vec3(float(v.x), float(v.y), float(v.z)); }

void tangents(const DVec3& n, DVec3& s, DVec3& t) {
  const double sign = std::copysign(1.0, n.z);
  const double a = -1.0 / (sign + n.z);
  const double b = n.x * n.y * a;
  s = DVec3(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
  t = DVec3(b, sign + n.y * n.y * a, -n.y);
}

template <typename T>
V3<T> lift(const DVec3& v) {
  return V3<T>(T(v.x), T(v.y), T(v.z));
}

// Bilinear texture lookup (Texture::eval's arithmetic) over a scalar type, so
// the derivative of a normal map with respect to the chart is exact.
template <typename T>
void texture_eval(const Texture& tex, const T& u, const T& v, T out[3]) {
  const Mat3& m = tex.to_uv;  // column-major: m[col][row]
  const T qu = u * double(m[0][0]) + v * double(m[1][0]) + double(m[2][0]);
  const T qv = u * double(m[0][1]) + v * double(m[1][1]) + double(m[2][1]);
  const T x = qu * double(tex.width) - 0.5, y = qv * double(tex.height) - 0.5;
  const double x0 = std::floor(value(x)), y0 = std::floor(value(y));
  const T ax = x - x0, ay = y - y0;
  const Color c00 = tex.texel(int(x0), int(y0)), c10 = tex.texel(int(x0) + 1, int(y0));
  const Color c01 = tex.texel(int(x0), int(y0) + 1), c11 = tex.texel(int(x0) + 1, int(y0) + 1);
  for (int k = 0; k < 3; ++k) {
    out[k] = (1.0 - ax) * (1.0 - ay) * double(c00[k]) + ax * (1.0 - ay) * double(c10[k]) +
             (1.0 - ax) * ay * double(c01[k]) + ax * ay * double(c11[k]);
  }
}

// Chart of a specular vertex: (du, dv) -> position and unit shading normal.
template <typename T>
void chart(const ManifoldVertex& v, const T& du, const T& dv, V3<T>& p, V3<T>& n) {
  V3<T> dpdu;
  T uu(0.0), vv(0.0);
  if (v.sphere) {
    const V3<T> q = lift<T>(v.p - v.center) + lift<T>(v.e1) * du + lift<T>(v.e2) * dv;
    const V3<T> qn = normalize(q);
    p = lift<T>(v.center) + qn * v.radius;
    n = qn * v.normal_sign;
    if (v.nmap) {
      // Mitsuba 3's sphere parameterisation (scene.cpp): u = phi / 2pi, v = theta / pi
      dpdu = V3<T>(-qn.y, qn.x, T(0.0));
      uu = atan2(qn.y, qn.x) * (1.0 / (2.0 * kPiD));
      if (value(uu) < 0.0) uu = uu + 1.0;
      vv = acos(qn.z) * (1.0 / kPiD);
    }
  } else {
    p = lift<T>(v.p) + lift<T>(v.e1) * du + lift<T>(v.e2) * dv;
    const V3<T> N = lift<T>(v.nb) + lift<T>(v.dn1) * du + lift<T>(v.dn2) * dv;
    n = normalize(N) * v.normal_sign;
    if (v.nmap) {
      dpdu = lift<T>(v.dpdu);
      uu = v.uv0.x + du * v.duv1.x + dv * v.duv2.x;
      vv = v.uv0.y + du * v.duv1.y + dv * v.duv2.y;
    }
  }
  if (v.mf) {
    // Offset microfacet normal, fixed in a smooth frame of the shading normal.
    const V3<T> e = lift<T>(v.e1);
    const V3<T> s = normalize(e - n * dot(n, e));
    const V3<T> t = cross(n, s);
    n = normalize(s * v.m_local.x + t * v.m_local.y + n * v.m_local.z);
  }
  if (v.nmap) {
    // Tangent-space normal in the shading frame (s along dp/du), as BSDFSet::resolve.
    const V3<T> s = normalize(dpdu - n * dot(n, dpdu));
    const V3<T> t = cross(n, s);
    T c[3];
    texture_eval<T>(*v.nmap, uu, vv, c);
    n = normalize(s * (c[0] * 2.0 - 1.0) + t * (c[1] * 2.0 - 1.0) + n * (c[2] * 2.0 - 1.0));
  }
}

// The two constraint values of one vertex (method-notes Sec. 2). Returns false
// when refraction is impossible (total internal reflection).
template <typename T>
bool vertex_constraint(const V3<T>& xp, const V3<T>& x, const V3<T>& n, const V3<T>& xn,
                       bool reflect, double eta, ConstraintForm form, const DVec3& tref_d, T out[2]) {
  const V3<T> wi = normalize(xp - x), wo = normalize(xn - x);
  const V3<T> tref = lift<T>(tref_d);
  const V3<T> s = normalize(tref - n * dot(n, tref));
  const V3<T> t = cross(n, s);
  const T ci = dot(wi, n);
  const bool outside = value(ci) > 0.0;
  if (form == ConstraintForm::HalfVector) {
    // Generalised half vector h ~ eta_i w_i + eta_o w_o (Walter 2007 Eq. 16);
    // at a solution h is parallel to n.
    V3<T> h;
    if (reflect) {
      h = wi + wo;
    } else {
      const double eta_i = outside ? 1.0 : eta, eta_o = outside ? eta : 1.0;
      h = wi * eta_i + wo * eta_o;
    }
    h = normalize(h);
    out[0] = dot(h, s);
    out[1] = dot(h, t);
    return true;
  }
  V3<T> ideal;
  if (reflect) {
    ideal = n * (ci * 2.0) - wi;
  } else {
    // Snell's law in vector form: w_t = -w_i / eta + (cos_i / eta - cos_t) n,
    // eta = eta_t / eta_i, n on the side of w_i.
    const double eta_rel = outside ? eta : 1.0 / eta;
    const V3<T> nn = outside ? n : -n;
    const T c = outside ? ci : -ci;
    const T sin2t = (1.0 - c * c) / (eta_rel * eta_rel);
    if (!(value(sin2t) < 1.0)) return false;
    const T ct = sqrt(1.0 - sin2t);
    ideal = wi * (-1.0 / eta_rel) + nn * (c / eta_rel - ct);
  }
  if (form == ConstraintForm::Direction) {
    // Tangential components of w_o - w_o': the angle difference measured in a
    // chart without the pole singularity of (theta, phi) at normal incidence.
    const V3<T> d = wo - ideal;
    out[0] = dot(d, s);
    out[1] = dot(d, t);
  } else {
    // SMS's angle difference: spherical coordinates in the shading frame.
    const T tho = acos(dot(wo, n)), thi = acos(dot(ideal, n));
    const T pho = atan2(dot(wo, t), dot(wo, s)), phi = atan2(dot(ideal, t), dot(ideal, s));
    T dphi = pho - phi;
    if (value(dphi) > kPiD) dphi = dphi - 2.0 * kPiD;
    if (value(dphi) < -kPiD) dphi = dphi + 2.0 * kPiD;
    out[0] = tho - thi;
    out[1] = dphi;
  }
  return true;
}

// 2x2 helpers (row-major).
inline double det2(const double* m) { return m[0] * m[3] - m[1] * m[2]; }
inline bool inv2(const double* m, double* r, double min_det) {
  const double d = det2(m);
  const double scale = std::abs(m[0]) + std::abs(m[1]) + std::abs(m[2]) + std::abs(m[3]);
  if (!(std::abs(d) > min_det * scale * scale) || !std::isfinite(d)) return false;
  const double id = 1.0 / d;
  r[0] = m[3] * id; r[1] = -m[1] * id; r[2] = -m[2] * id; r[3] = m[0] * id;
  return true;
}
// C (2 x m) = A (2x2) * B (2 x m)
inline void mul2(const double* a, const double* b, double* c, int m) {
  for (int j = 0; j < m; ++j) {
    c[j] = a[0] * b[j] + a[1] * b[m + j];
    c[m + j] = a[2] * b[j] + a[3] * b[m + j];
  }
}

}  // namespace

// Put a sphere vertex at the point of direction q from the centre: tangent
// chart and (possibly perturbed) normal.
static void place_on_sphere(ManifoldVertex& v, const DVec3& q) {
  v.p = v.center + q * v.radius;
  DVec3 t1, t2;
  tangents(q, t1, t2);
  v.e1 = t1 * v.radius;
  v.e2 = t2 * v.radius;
  v.n = q * v.normal_sign;
  if (v.nmap || v.mf) {
    V3<double> pp, nn;
    chart<double>(v, 0.0, 0.0, pp, nn);
    v.n = DVec3(nn.x, nn.y, nn.z);
  }
}

bool ManifoldWalk::scatter(const DVec3& wi, const DVec3& n, double eta, bool reflect, DVec3& wo) {
  const double ci = glm::dot(wi, n);
  if (reflect) {
    wo = 2.0 * ci * n - wi;
  } else {
    // Snell's law in vector form (as vertex_constraint), n flipped to the side of wi.
    const double eta_rel = ci > 0.0 ? eta : 1.0 / eta;
    const DVec3 nn = ci > 0.0 ? n : -n;
    const double c = std::abs(ci);
    const double sin2t = (1.0 - c * c) / (eta_rel * eta_rel);
    if (sin2t >= 1.0) return false;
    wo = -wi / eta_rel + nn * (c / eta_rel - std::sqrt(1.0 - sin2t));
  }
  wo = glm::normalize(wo);
  return true;
}

ManifoldVertex ManifoldWalk::moved(const ManifoldVertex& v, double du, double dv) {
  V3<double> p, n;
  chart<double>(v, du, dv, p, n);
  ManifoldVertex r = v;
  r.p = DVec3(p.x, p.y, p.z);
  r.n = DVec3(n.x, n.y, n.z);
  return r;
}

bool ManifoldWalk::make_vertex(const SurfaceInteraction& si, bool reflect, ManifoldVertex& v,
                               const Vec2* offset_u) const {
  if (!si.valid) return false;
  const Shape& s = scene_.shapes[size_t(si.shape)];
  const BSDFContext ctx = scene_.bsdfs.resolve(s.bsdf, si);
  if (!ctx.leaf) return false;
  const BSDF& b = *ctx.leaf;
  // The normal map on the way to the leaf, if any (resolve applied it to ctx.frame).
  const Texture* nmap = nullptr;
  for (int id = s.bsdf, guard = 0; id >= 0 && guard < 16; ++guard) {
    const BSDF& node = scene_.bsdfs.nodes[size_t(id)];
    if (node.type == BSDFType::NormalMap) {
      if (nmap) return false;  // nested normal maps: not supported
      nmap = &scene_.bsdfs.textures[size_t(node.normalmap)];
      id = node.nested;
    } else if (node.type == BSDFType::TwoSided) {
      id = glm::dot(si.wi, si.sh.n) < 0.f ? node.back : node.front;
    } else {
      break;
    }
  }
  if (nmap && nmap->kind != Texture::Kind::Bitmap) nmap = nullptr;
  // Smooth (delta) interfaces only: the path tracer samples rough ones as glossy,
  // and chain ownership must match what it samples as specular.
  const bool glossy = (b.type == BSDFType::RoughDielectric || b.type == BSDFType::RoughConductor) &&
                      std::max(b.mf.ax, b.mf.ay) < cfg_.glossy_threshold;
  if (glossy && (!offset_u || nmap)) return false;  // offsets needed; not combined with normal maps
  const bool is_dielectric = b.type == BSDFType::Dielectric || (glossy && b.type == BSDFType::RoughDielectric);
  const bool is_conductor = b.type == BSDFType::Conductor || (glossy && b.type == BSDFType::RoughConductor);
  if (!(is_dielectric || (is_conductor && reflect))) return false;
  v = ManifoldVertex();
  v.shape = si.shape;
  v.prim = si.prim;
  v.reflect = reflect;
  v.eta = is_dielectric ? double(b.eta) : 1.0;
  v.dielectric = is_dielectric;
  v.p = to_d(si.p);
  v.ng = to_d(si.ng);
  v.uv = si.uv;
  v.nmap = nmap;
  if (glossy) {
    v.mf = &b.mf;
    v.offset_u = *offset_u;
    float pdf;
    const Vec3 m = b.mf.sample_dcos(*offset_u, pdf);
    v.m_local = glm::dvec3(m.x, m.y, m.z);
  }
  v.normal_sign = s.flip_normals ? -1.0 : 1.0;
  if (s.kind == Shape::Kind::Sphere) {
    v.sphere = true;
    v.center = to_d(s.center);
    v.radius = double(s.radius);
    place_on_sphere(v, glm::normalize(v.p - v.center));
  } else {
    const glm::uvec3 tri = s.indices[size_t(si.prim)];
    const DVec3 p0 = to_d(s.positions[tri.x]), p1 = to_d(s.positions[tri.y]), p2 = to_d(s.positions[tri.z]);
    const double b1 = si.bary.x, b2 = si.bary.y;
    v.p = p0 + b1 * (p1 - p0) + b2 * (p2 - p0);
    v.e1 = p1 - p0;
    v.e2 = p2 - p0;
    if (!s.normals.empty()) {
      const DVec3 n0 = to_d(s.normals[tri.x]), n1 = to_d(s.normals[tri.y]), n2 = to_d(s.normals[tri.z]);
      v.nb = n0 + b1 * (n1 - n0) + b2 * (n2 - n0);
      v.dn1 = n1 - n0;
      v.dn2 = n2 - n0;
    } else {
      v.nb = glm::normalize(glm::cross(v.e1, v.e2));
    }
    v.n = glm::normalize(v.nb) * v.normal_sign;
    if (v.mf) {
      V3<double> pp, nn;
      chart<double>(v, 0.0, 0.0, pp, nn);
      v.n = DVec3(nn.x, nn.y, nn.z);
    }
    if (v.nmap) {
      // uv chart and dp/du exactly as make_interaction computes them
      v.dpdu = v.e1;
      if (!s.uvs.empty()) {
        const glm::dvec2 u0(s.uvs[tri.x].x, s.uvs[tri.x].y), u1(s.uvs[tri.y].x, s.uvs[tri.y].y),
            u2(s.uvs[tri.z].x, s.uvs[tri.z].y);
        v.duv1 = u1 - u0;
        v.duv2 = u2 - u0;
        v.uv0 = u0 + b1 * v.duv1 + b2 * v.duv2;
        const double det = v.duv1.x * v.duv2.y - v.duv1.y * v.duv2.x;
        if (std::abs(det) > 1e-12) v.dpdu = (v.duv2.y * v.e1 - v.duv1.y * v.e2) / det;
      } else {
        v.uv0 = glm::dvec2(b1, b2);
        v.duv1 = glm::dvec2(1.0, 0.0);
        v.duv2 = glm::dvec2(0.0, 1.0);
      }
      V3<double> pp, nn;
      chart<double>(v, 0.0, 0.0, pp, nn);
      v.n = DVec3(nn.x, nn.y, nn.z);
    }
  }
  return true;
}

bool ManifoldWalk::make_vertex_refined(const SurfaceInteraction& si_in, const DVec3& o,
                                       const DVec3& d, bool reflect, ManifoldVertex& v,
                                       const Vec2* offset_u) const {
  if (!si_in.valid) return false;
  SurfaceInteraction si = si_in;
  const Shape& s = scene_.shapes[size_t(si.shape)];
  if (s.kind == Shape::Kind::Sphere) {
    // Ray-sphere in double; keep the root nearest to Embree's distance.
    if (!make_vertex(si, reflect, v, offset_u)) return false;
    const DVec3 oc = o - v.center;
    const double b = glm::dot(oc, d), cc = glm::dot(oc, oc) - v.radius * v.radius;
    const double disc = b * b - cc;
    if (disc < 0.0) return true;
    const double sq = std::sqrt(disc);
    const double t0 = -b - sq, t1 = -b + sq;
    const double t = std::abs(t0 - double(si.t)) < std::abs(t1 - double(si.t)) ? t0 : t1;
    place_on_sphere(v, glm::normalize(o + t * d - v.center));
    return true;
  }
  if (!make_vertex(si, reflect, v, offset_u)) return false;
  // Ray-plane of the hit triangle in double, barycentrics by projection.
  const glm::uvec3 tri = s.indices[size_t(si.prim)];
  const DVec3 p0 = to_d(s.positions[tri.x]);
  const DVec3 nrm = glm::cross(v.e1, v.e2);
  const double den = glm::dot(d, nrm);
  if (std::abs(den) < 1e-300) return true;
  const double t = glm::dot(p0 - o, nrm) / den;
  const DVec3 p = o + t * d;
  const double n2 = glm::dot(nrm, nrm);
  const DVec3 q = p - p0;
  const double b1 = glm::dot(glm::cross(q, v.e2), nrm) / n2;
  const double b2 = glm::dot(glm::cross(v.e1, q), nrm) / n2;
  v.p = p0 + b1 * v.e1 + b2 * v.e2;
  if (!s.normals.empty()) {
    const DVec3 n0 = to_d(s.normals[tri.x]);
    v.nb = n0 + b1 * v.dn1 + b2 * v.dn2;
    v.n = glm::normalize(v.nb) * v.normal_sign;
  }
  if (v.nmap || v.mf) {
    if (v.nmap)
      v.uv0 = s.uvs.empty() ? glm::dvec2(b1, b2)
                            : glm::dvec2(s.uvs[tri.x].x, s.uvs[tri.x].y) + b1 * v.duv1 + b2 * v.duv2;
    V3<double> pp, nn;
    chart<double>(v, 0.0, 0.0, pp, nn);
    v.n = DVec3(nn.x, nn.y, nn.z);
  }
  return true;
}

bool ManifoldWalk::constraints(const ManifoldChain& c, std::vector<double>& C) const {
  const size_t n = c.v.size();
  C.assign(2 * n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    const DVec3 xp = i == 0 ? c.xD : c.v[i - 1].p;
    const DVec3 xn = i + 1 == n ? c.xL : c.v[i + 1].p;
    double out[2];
    const V3<double> x = lift<double>(c.v[i].p), nn = lift<double>(c.v[i].n);
    if (!vertex_constraint<double>(lift<double>(xp), x, nn, lift<double>(xn), c.v[i].reflect,
                                   c.v[i].eta, cfg_.form, c.v[i].e1, out))
      return false;
    C[2 * i] = out[0];
    C[2 * i + 1] = out[1];
  }
  return true;
}

bool ManifoldWalk::jacobian(const ManifoldChain& c, std::vector<double>& A, std::vector<double>& B,
                            std::vector<double>& D, double dCn_dL[4], double dC1_dD[4]) const {
  using D6 = Dual<6>;
  using D2 = Dual<2>;
  const size_t n = c.v.size();
  A.assign(4 * n, 0.0);
  B.assign(4 * n, 0.0);
  D.assign(4 * n, 0.0);
  // Each chart once, differentiated with respect to its own (du, dv); constraint
  // i sees three of them, so their derivatives are placed in slots 0-1 (x_{i-1}),
  // 2-3 (x_i) and 4-5 (x_{i+1}) of a 6-variable dual: the same exact blocks as
  // differentiating the three charts inside the constraint, at a third of the cost.
  thread_local std::vector<V3<D2>> P, N;
  P.resize(n);
  N.resize(n);
  for (size_t i = 0; i < n; ++i) chart<D2>(c.v[i], D2::var(0.0, 0), D2::var(0.0, 1), P[i], N[i]);
  auto embed = [](const V3<D2>& a, int slot) {
    auto one = [slot](const D2& x) {
      D6 r(x.v);
      r.d[size_t(slot)] = x.d[0];
      r.d[size_t(slot + 1)] = x.d[1];
      return r;
    };
    return V3<D6>(one(a.x), one(a.y), one(a.z));
  };
  for (size_t i = 0; i < n; ++i) {
    const V3<D6> xp = i == 0 ? lift<D6>(c.xD) : embed(P[i - 1], 0);
    const V3<D6> x = embed(P[i], 2), nx = embed(N[i], 2);
    const V3<D6> xn = i + 1 == n ? lift<D6>(c.xL) : embed(P[i + 1], 4);
    D6 out[2];
    if (!vertex_constraint<D6>(xp, x, nx, xn, c.v[i].reflect, c.v[i].eta, cfg_.form, c.v[i].e1, out))
      return false;
    for (int r = 0; r < 2; ++r) {
      for (int k = 0; k < 2; ++k) {
        A[4 * i + 2 * r + k] = out[r].d[size_t(k)];
        B[4 * i + 2 * r + k] = out[r].d[size_t(2 + k)];
        D[4 * i + 2 * r + k] = out[r].d[size_t(4 + k)];
      }
    }
  }
  // Endpoint derivatives in orthonormal tangent charts (unit area per du dv).
  if (dCn_dL) {
    DVec3 tL1, tL2;
    tangents(glm::normalize(c.nL), tL1, tL2);
    const size_t i = n - 1;
    V3<D2> xp, np, x, nx;
    if (i == 0) xp = lift<D2>(c.xD);
    else chart<D2>(c.v[i - 1], D2(0.0), D2(0.0), xp, np);
    chart<D2>(c.v[i], D2(0.0), D2(0.0), x, nx);
    const V3<D2> xl = lift<D2>(c.xL) + lift<D2>(tL1) * D2::var(0.0, 0) + lift<D2>(tL2) * D2::var(0.0, 1);
    D2 out[2];
    if (!vertex_constraint<D2>(xp, x, nx, xl, c.v[i].reflect, c.v[i].eta, cfg_.form, c.v[i].e1, out))
      return false;
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 2; ++k) dCn_dL[2 * r + k] = out[r].d[size_t(k)];
  }
  if (dC1_dD) {
    DVec3 tD1, tD2;
    tangents(glm::normalize(c.nD), tD1, tD2);
    V3<D2> x, nx, xn, nn;
    chart<D2>(c.v[0], D2(0.0), D2(0.0), x, nx);
    if (n == 1) xn = lift<D2>(c.xL);
    else chart<D2>(c.v[1], D2(0.0), D2(0.0), xn, nn);
    const V3<D2> xd = lift<D2>(c.xD) + lift<D2>(tD1) * D2::var(0.0, 0) + lift<D2>(tD2) * D2::var(0.0, 1);
    D2 out[2];
    if (!vertex_constraint<D2>(xd, x, nx, xn, c.v[0].reflect, c.v[0].eta, cfg_.form, c.v[0].e1, out))
      return false;
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 2; ++k) dC1_dD[2 * r + k] = out[r].d[size_t(k)];
  }
  return true;
}

bool ManifoldWalk::solve_tridiagonal(const std::vector<double>& A, const std::vector<double>& B,
                                     const std::vector<double>& D, std::vector<double>& R, int m) const {
  // Block Thomas algorithm: forward elimination then back substitution, O(n).
  const size_t n = B.size() / 4;
  thread_local std::vector<double> Bp, inv, tmp;
  Bp = B;
  inv.resize(4 * n);
  const size_t rs = size_t(2 * m);
  tmp.resize(rs);
  double M[4];
  for (size_t i = 0; i < n; ++i) {
    if (i > 0) {
      // M = A_i inv(Bp_{i-1});  Bp_i -= M D_{i-1};  R_i -= M R_{i-1}
      const double* a = &A[4 * i];
      const double* bi = &inv[4 * (i - 1)];
      M[0] = a[0] * bi[0] + a[1] * bi[2];
      M[1] = a[0] * bi[1] + a[1] * bi[3];
      M[2] = a[2] * bi[0] + a[3] * bi[2];
      M[3] = a[2] * bi[1] + a[3] * bi[3];
      double md[4];
      mul2(M, &D[4 * (i - 1)], md, 2);
      for (int k = 0; k < 4; ++k) Bp[4 * i + k] -= md[k];
      mul2(M, &R[rs * (i - 1)], tmp.data(), m);
      for (size_t k = 0; k < rs; ++k) R[rs * i + k] -= tmp[k];
    }
    if (!inv2(&Bp[4 * i], &inv[4 * i], cfg_.min_det)) return false;
  }
  for (size_t ii = n; ii-- > 0;) {
    if (ii + 1 < n) {
      mul2(&D[4 * ii], &R[rs * (ii + 1)], tmp.data(), m);
      for (size_t k = 0; k < rs; ++k) R[rs * ii + k] -= tmp[k];
    }
    mul2(&inv[4 * ii], &R[rs * ii], tmp.data(), m);
    for (size_t k = 0; k < rs; ++k) R[rs * ii + k] = tmp[k];
  }
  for (double x : R)
    if (!std::isfinite(x)) return false;
  return true;
}

bool ManifoldWalk::reproject(const ManifoldChain& from, const std::vector<DVec3>& targets,
                             ManifoldChain& out, WalkFailure& why) const {
  out = from;
  DVec3 origin = from.xD;
  DVec3 origin_n = from.nD;
  const float scale = std::max(1.f, scene_.bound_radius());
  for (size_t i = 0; i < targets.size(); ++i) {
    // Aim from the offset origin itself, so the offset does not shift the landing point.
    const Vec3 o = offset_ray_origin(to_f(origin), to_f(origin_n), to_f(targets[i] - origin));
    DVec3 d = targets[i] - to_d(o);
    const double len = glm::length(d);
    if (!(len > cfg_.min_segment * scale)) {
      why = WalkFailure::VanishingSegment;
      return false;
    }
    d /= len;
    const SurfaceInteraction si = scene_.intersect(o, to_f(d), 0.f, kInf);
    if (!si.valid || si.shape != from.v[i].shape) {
      why = WalkFailure::LeftSurface;
      return false;
    }
    if (!make_vertex_refined(si, to_d(o), d, from.v[i].reflect, out.v[i],
                             from.v[i].mf ? &from.v[i].offset_u : nullptr)) {
      why = WalkFailure::NotSpecular;
      return false;
    }
    origin = out.v[i].p;
    origin_n = out.v[i].ng;
  }
  // The last segment, to the light, must not vanish either (x_L on the surface).
  if (!(glm::length(from.xL - origin) > cfg_.min_segment * scale)) {
    why = WalkFailure::VanishingSegment;
    return false;
  }
  return true;
}

namespace {
// An iteration after the first whose line search rejected `rejected` tries
// stops the walks limited to fewer halvings (WalkResult::limited_tries): each
// such limit H, not yet stopped, ends here after H + 1 tries of this iteration.
void note_rejections(WalkResult& res, int iteration, int tries_before, int rejected) {
  if (iteration == 0) return;
  for (int h = res.later_rejections; h < std::min(rejected, kFullSearch); ++h)
    res.limited_tries[size_t(h)] = tries_before + h + 1;
  res.later_rejections = std::max(res.later_rejections, rejected);
}
}  // namespace

WalkResult ManifoldWalk::solve(ManifoldChain& chain) const {
  WalkResult res = solve_walk(chain);
  // The limits that never stopped the walk take all of its tries.
  for (int h = std::min(res.later_rejections, kFullSearch); h < kHalvingSlots; ++h)
    res.limited_tries[size_t(h)] = res.reprojections;
  return res;
}

WalkResult ManifoldWalk::solve_walk(ManifoldChain& chain) const {
  WalkResult res;
  const size_t n = chain.v.size();
  if (n == 0) {
    res.failure = WalkFailure::NotSpecular;
    return res;
  }
  // Scratch reused across walks of this thread (no allocation per trial).
  thread_local std::vector<double> C, A, B, D, R, Ct;
  thread_local std::vector<DVec3> targets;
  thread_local ManifoldChain trial;
  if (!constraints(chain, C)) {
    res.failure = WalkFailure::TotalInternalReflection;
    return res;
  }
  auto max_abs = [](const std::vector<double>& v) {
    double m = 0.0;
    for (double x : v) m = std::max(m, std::abs(x));
    return m;
  };
  double err = max_abs(C);
  if (cfg_.record_residuals) res.residuals.push_back(err);
  double beta = 1.0;
  targets.resize(n);
  const double scale = std::max(1.0, double(scene_.bound_radius()));
  for (int it = 0; it < cfg_.max_iterations; ++it) {
    if (err < cfg_.threshold) break;
    if (!jacobian(chain, A, B, D, nullptr, nullptr)) {  // the walk needs only the blocks
      res.failure = WalkFailure::TotalInternalReflection;
      return res;
    }
    R.assign(2 * n, 0.0);
    for (size_t k = 0; k < 2 * n; ++k) R[k] = -C[k];
    if (!solve_tridiagonal(A, B, D, R, 1)) {
      res.failure = WalkFailure::SingularJacobian;
      return res;
    }
    bool accepted = false;
    // Iterations after the first may be limited to step_halvings halvings below
    // the beta they start from (off by default): it saves the long searches of
    // walks that fail anyway (double_slabs: half the tries), but walks towards a
    // light near a mirror need them (design-notes, "Step control").
    const double floor_it = it == 0 || cfg_.step_halvings < 0
                                ? cfg_.min_step
                                : std::max(cfg_.min_step, std::ldexp(beta, -cfg_.step_halvings));
    const int tries_before = res.reprojections;
    while (!accepted) {
      double moved = 0.0;
      for (size_t i = 0; i < n; ++i) {
        V3<double> p, nn;
        chart<double>(chain.v[i], beta * R[2 * i], beta * R[2 * i + 1], p, nn);
        targets[i] = DVec3(p.x, p.y, p.z);
        moved = std::max(moved, glm::length(targets[i] - chain.v[i].p));
      }
      if (moved < 1e-12 * scale) {
        note_rejections(res, it, tries_before, res.reprojections - tries_before);
        res.failure = WalkFailure::Stuck;
        res.iterations = it + 1;
        return res;
      }
      WalkFailure why = WalkFailure::None;
      res.reprojections++;
      // Accept a step that lands on the surfaces and does not blow the residual
      // up (a backtracking line search on beta; 1.5x tolerates the max-norm's
      // non-monotone decrease): plain Newton overshoots where the constraints
      // are far from linear, e.g. with the light near the specular surface.
      const bool landed = reproject(chain, targets, trial, why);
      if (!landed) res.off_surface++;
      if (landed && constraints(trial, Ct) && max_abs(Ct) < 1.5 * err) {
        accepted = true;
        chain = trial;
        C = Ct;
        err = max_abs(C);
        beta = std::min(1.0, 2.0 * beta);
      } else {
        beta *= 0.5;
        if (beta < floor_it) {
          note_rejections(res, it, tries_before, res.reprojections - tries_before);
          res.failure = why == WalkFailure::None ? WalkFailure::StepTooSmall : why;
          res.iterations = it + 1;
          return res;
        }
      }
    }
    note_rejections(res, it, tries_before, res.reprojections - tries_before - 1);
    res.iterations = it + 1;
    if (cfg_.record_residuals) res.residuals.push_back(err);
  }
  if (!(err < cfg_.threshold)) {
    res.failure = WalkFailure::MaxIterations;
    return res;
  }
  // The converged chain must scatter as its letters say: reflection keeps both
  // directions on one side of the surface, refraction crosses it.
  for (size_t i = 0; i < n; ++i) {
    const DVec3 xp = i == 0 ? chain.xD : chain.v[i - 1].p;
    const DVec3 xn = i + 1 == n ? chain.xL : chain.v[i + 1].p;
    const double a = glm::dot(xp - chain.v[i].p, chain.v[i].ng);
    const double b = glm::dot(xn - chain.v[i].p, chain.v[i].ng);
    const double as = glm::dot(xp - chain.v[i].p, chain.v[i].n);
    const double bs = glm::dot(xn - chain.v[i].p, chain.v[i].n);
    const bool same = a * b > 0.0 && as * bs > 0.0;
    const bool opposite = a * b < 0.0 && as * bs < 0.0;
    bool ok = chain.v[i].reflect ? same : opposite;
    if (chain.v[i].nmap || chain.v[i].mf) {
      // Sides against the unperturbed shading normal too: the path tracer
      // rejects a direction on different sides of the perturbed and the
      // unperturbed normal (BSDFSet::sample), and a rough interface reflects
      // or transmits relative to its macro-surface.
      V3<double> pp, nb;
      ManifoldVertex base = chain.v[i];
      base.nmap = nullptr;
      base.mf = nullptr;
      chart<double>(base, 0.0, 0.0, pp, nb);
      const DVec3 nbase(nb.x, nb.y, nb.z);
      const double ab = glm::dot(xp - chain.v[i].p, nbase), bb = glm::dot(xn - chain.v[i].p, nbase);
      ok = ok && (chain.v[i].reflect ? ab * bb > 0.0 : ab * bb < 0.0);
      if (chain.v[i].nmap) ok = ok && bb * bs > 0.0;
    }
    if (!ok) {
      res.failure = WalkFailure::WrongHemisphere;
      return res;
    }
  }
  res.converged = true;
  return res;
}

namespace {
// |d omega / dA| for omega = normalize(x_v - from), x_v moving with the 2x2
// block X = d(chart of v) / d(orthonormal endpoint chart): the solid angle
// swept per unit area at the moving endpoint (method-notes Sec. 4).
double swept_solid_angle(const ManifoldVertex& v, const DVec3& from, const double* X) {
  using D2 = Dual<2>;
  V3<D2> x, nrm;
  chart<D2>(v, D2::var(0.0, 0), D2::var(0.0, 1), x, nrm);
  const V3<D2> w = normalize(x - lift<D2>(from));
  DVec3 m0, m1;
  const D2 comp[3] = {w.x, w.y, w.z};
  for (int r = 0; r < 3; ++r) {
    m0[r] = comp[r].d[0] * X[0] + comp[r].d[1] * X[2];
    m1[r] = comp[r].d[0] * X[1] + comp[r].d[1] * X[3];
  }
  return std::abs(glm::dot(glm::cross(m0, m1), DVec3(w.x.v, w.y.v, w.z.v)));
}
}  // namespace

bool ManifoldWalk::geometry_area(const ManifoldChain& c, double& G) const {
  const size_t n = c.v.size();
  std::vector<double> A, B, D;
  double dL[4];
  if (!jacobian(c, A, B, D, dL, nullptr)) return false;
  // dX/dx_L = -J^{-1} dC/dx_L; only block n-1 of the right-hand side is non-zero.
  std::vector<double> R(4 * n, 0.0);
  for (int k = 0; k < 4; ++k) R[4 * (n - 1) + size_t(k)] = -dL[k];
  if (!solve_tridiagonal(A, B, D, R, 2)) return false;
  G = swept_solid_angle(c.v[0], c.xD, &R[0]);  // omega_D moves with x_1
  return std::isfinite(G);
}

bool ManifoldWalk::geometry_point(const ManifoldChain& c, double& G) const {
  const size_t n = c.v.size();
  std::vector<double> A, B, D;
  double dD[4];
  if (!jacobian(c, A, B, D, nullptr, dD)) return false;
  // dX/dx_D = -J^{-1} dC/dx_D; only block 0 of the right-hand side is non-zero.
  std::vector<double> R(4 * n, 0.0);
  for (int k = 0; k < 4; ++k) R[size_t(k)] = -dD[k];
  if (!solve_tridiagonal(A, B, D, R, 2)) return false;
  G = swept_solid_angle(c.v[n - 1], c.xL, &R[4 * (n - 1)]);  // omega_L moves with x_n
  return std::isfinite(G);
}

bool ManifoldWalk::trace_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir,
                              const std::string& tau, ManifoldChain& chain, WalkFailure& why,
                              const std::vector<Vec2>* offsets) const {
  chain.xD = xD;
  chain.nD = nD;
  chain.v.clear();
  DVec3 o = xD, on = nD, d = glm::normalize(dir);
  for (char letter : tau) {
    const Vec3 of = offset_ray_origin(to_f(o), to_f(on), to_f(d));
    const SurfaceInteraction si = scene_.intersect(of, to_f(d), 0.f, kInf);
    if (!si.valid) {
      why = WalkFailure::LeftSurface;
      return false;
    }
    ManifoldVertex v;
    const size_t idx = chain.v.size();
    const Vec2* off = offsets && idx < offsets->size() ? &(*offsets)[idx] : nullptr;
    if (!make_vertex(si, letter == 'R', v, off)) {
      why = WalkFailure::NotSpecular;
      return false;
    }
    if (!scatter(-d, v.n, v.eta, letter == 'R', d)) {
      why = WalkFailure::TotalInternalReflection;
      return false;
    }
    o = v.p;
    on = v.ng;
    chain.v.push_back(v);
  }
  return true;
}

}  // namespace mpg
