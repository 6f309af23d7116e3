#include "scene/scene.h"

#include <cmath>
#include <stdexcept>

#include "core/warp.h"

namespace mpg {

namespace {
thread_local std::string g_embree_error;
void embree_error(void*, RTCError code, const char* str) {
  g_embree_error = std::string("Embree error ") + std::to_string(int(code)) + ": " + (str ? str : "");
}

// Nearest root of |o + t d - c|^2 = r^2 in (tmin, tmax), in double, with the
// cancellation-free form of the quadratic (Haines et al., "Precision improvements
// for ray/sphere intersection", Ray Tracing Gems ch. 7): the discriminant from
// the perpendicular distance, the second root as c/q. `inv_a` = 1 / |d|^2.
inline bool hit_sphere(const DirectSphere& s, const Vec3& o, const Vec3& d, double inv_a, float tmin,
                       float tmax, double& t) {
  const double fx = double(o.x) - s.cx, fy = double(o.y) - s.cy, fz = double(o.z) - s.cz;
  const double dx = d.x, dy = d.y, dz = d.z;
  const double b = -(fx * dx + fy * dy + fz * dz);  // -f.d
  const double c = fx * fx + fy * fy + fz * fz - s.r2;
  const double ba = b * inv_a;
  // r^2 - |f + (b/a) d|^2, times a
  const double px = fx + ba * dx, py = fy + ba * dy, pz = fz + ba * dz;
  const double disc = (s.r2 - (px * px + py * py + pz * pz)) / inv_a;
  if (!(disc >= 0.0)) return false;
  const double q = b + std::copysign(std::sqrt(disc), b);
  double t0 = c / q, t1 = q * inv_a;
  if (!(q != 0.0)) t0 = t1 = ba;
  if (t0 > t1) std::swap(t0, t1);
  if (t0 > double(tmin) && t0 < double(tmax)) { t = t0; return true; }
  if (t1 > double(tmin) && t1 < double(tmax)) { t = t1; return true; }
  return false;
}
inline double inv_len2(const Vec3& d) {
  return 1.0 / (double(d.x) * d.x + double(d.y) * d.y + double(d.z) * d.z);
}
}  // namespace

Scene::Scene() {
  device_ = rtcNewDevice("threads=1");  // BVH build only; rendering threads are ours
  if (!device_) throw std::runtime_error("could not create an Embree device");
  rtcSetDeviceErrorFunction(device_, embree_error, nullptr);
}

Scene::~Scene() {
  if (rtc_) rtcReleaseScene(rtc_);
  if (device_) rtcReleaseDevice(device_);
}

int Scene::add_shape(Shape s) {
  if (committed_) throw std::runtime_error("scene already committed");
  s.finalize();
  shapes.push_back(std::move(s));
  return int(shapes.size()) - 1;
}

int Scene::add_emitter(Emitter e) {
  if (committed_) throw std::runtime_error("scene already committed");
  emitters.push_back(std::move(e));
  const int id = int(emitters.size()) - 1;
  if (emitters.back().type == Emitter::Type::Area) shapes[size_t(emitters.back().shape)].emitter = id;
  return id;
}

void Scene::commit() {
  if (committed_) return;
  g_embree_error.clear();
  rtc_ = rtcNewScene(device_);
  rtcSetSceneBuildQuality(rtc_, RTC_BUILD_QUALITY_HIGH);
  bbox_min = Vec3(kInf);
  bbox_max = Vec3(-kInf);
  direct_spheres_.clear();
  rtc_empty_ = true;
  size_t n_spheres = 0;
  for (const Shape& s : shapes) n_spheres += s.kind == Shape::Kind::Sphere;
  const bool direct = n_spheres <= kMaxDirectSpheres;
  for (size_t i = 0; i < shapes.size(); ++i) {
    shapes[i].needs_uv = bsdfs.uses_uv(shapes[i].bsdf);
    const Shape& s = shapes[i];
    RTCGeometry g;
    if (s.kind == Shape::Kind::Sphere && direct) {
      direct_spheres_.push_back({double(s.center.x), double(s.center.y), double(s.center.z),
                                 double(s.radius) * double(s.radius), unsigned(i)});
      bbox_min = glm::min(bbox_min, s.center - Vec3(s.radius));
      bbox_max = glm::max(bbox_max, s.center + Vec3(s.radius));
      continue;
    } else if (s.kind == Shape::Kind::Sphere) {
      g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_SPHERE_POINT);
      float* v = (float*)rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT4,
                                                 4 * sizeof(float), 1);
      v[0] = s.center.x; v[1] = s.center.y; v[2] = s.center.z; v[3] = s.radius;
      bbox_min = glm::min(bbox_min, s.center - Vec3(s.radius));
      bbox_max = glm::max(bbox_max, s.center + Vec3(s.radius));
    } else {
      g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
      // One float of padding: Embree may read 16 bytes from the last vertex.
      float* v = (float*)rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                 3 * sizeof(float), s.positions.size() + 1);
      for (size_t k = 0; k < s.positions.size(); ++k) {
        v[3 * k] = s.positions[k].x; v[3 * k + 1] = s.positions[k].y; v[3 * k + 2] = s.positions[k].z;
        bbox_min = glm::min(bbox_min, s.positions[k]);
        bbox_max = glm::max(bbox_max, s.positions[k]);
      }
      unsigned* idx = (unsigned*)rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                         3 * sizeof(unsigned), s.indices.size());
      for (size_t k = 0; k < s.indices.size(); ++k) {
        idx[3 * k] = s.indices[k].x; idx[3 * k + 1] = s.indices[k].y; idx[3 * k + 2] = s.indices[k].z;
      }
    }
    rtcCommitGeometry(g);
    rtcAttachGeometryByID(rtc_, g, unsigned(i));
    rtcReleaseGeometry(g);
    rtc_empty_ = false;
  }
  rtcCommitScene(rtc_);
  if (!g_embree_error.empty()) throw std::runtime_error(g_embree_error);
  if (shapes.empty()) { bbox_min = Vec3(-1.f); bbox_max = Vec3(1.f); }

  // Light selection proportional to (approximate) emitted power.
  const float R = std::max(bound_radius(), 1e-3f);
  std::vector<float> w;
  light_index_.assign(emitters.size(), -1);
  light_list_.clear();
  infinite_emitters.clear();
  for (size_t i = 0; i < emitters.size(); ++i) {
    Emitter& e = emitters[i];
    float p = 0.f;
    switch (e.type) {
      case Emitter::Type::Area: p = mean(e.value) * shapes[size_t(e.shape)].area * kPi; break;
      case Emitter::Type::Point: p = 4.f * kPi * mean(e.value); break;
      case Emitter::Type::Spot: p = 2.f * kPi * (1.f - 0.5f * (e.cos_cutoff + e.cos_beam)) * mean(e.value); break;
      case Emitter::Type::Directional: p = kPi * R * R * mean(e.value); break;
      case Emitter::Type::Constant: p = 4.f * kPi * kPi * R * R * mean(e.value); break;
      case Emitter::Type::Envmap: p = 4.f * kPi * kPi * R * R * e.env.mean_value() * e.scale; break;
    }
    if (e.is_infinite()) infinite_emitters.push_back(int(i));
    e.power = p;
    if (std::isfinite(p) && p > 0.f) {
      light_index_[i] = int(light_list_.size());
      light_list_.push_back(int(i));
      w.push_back(p);
    }
  }
  light_dist_.build(w);
  committed_ = true;
}

SurfaceInteraction Scene::intersect(const Vec3& o, const Vec3& d, float tmin, float tmax) const {
  SurfaceInteraction si;
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  RTCRayHit rh;
  rh.ray.org_x = o.x; rh.ray.org_y = o.y; rh.ray.org_z = o.z;
  rh.ray.dir_x = d.x; rh.ray.dir_y = d.y; rh.ray.dir_z = d.z;
  rh.ray.tnear = tmin; rh.ray.tfar = tmax;
  rh.ray.mask = 0xffffffffu; rh.ray.flags = 0; rh.ray.time = 0.f;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  if (!rtc_empty_) rtcIntersect1(rtc_, &ctx, &rh);
  const double inv_a = inv_len2(d);
  for (const DirectSphere& s : direct_spheres_) {
    double t;
    if (hit_sphere(s, o, d, inv_a, tmin, rh.ray.tfar, t)) {
      rh.ray.tfar = float(t);
      rh.hit.geomID = s.shape;
      rh.hit.primID = 0;
    }
  }
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return si;
  return make_interaction(o, d, rh.ray.tfar, rh.hit.geomID, rh.hit.primID, rh.hit.u, rh.hit.v);
}

SurfaceInteraction Scene::make_interaction(const Vec3& o, const Vec3& d, float t, unsigned geom,
                                           unsigned prim, float bu, float bv) const {
  SurfaceInteraction si;
  const Shape& s = shapes[geom];
  si.valid = true;
  si.t = t;
  si.shape = int(geom);
  si.prim = int(prim);
  si.wi = -d;
  Vec3 ns;
  if (s.kind == Shape::Kind::Sphere) {
    const Vec3 p = o + d * t;
    const Vec3 q = glm::normalize(p - s.center);
    si.p = s.center + q * s.radius;  // reproject onto the exact sphere
    si.ng = q;
    ns = q;
    // Mitsuba 3's sphere parameterisation: u = phi / 2pi, v = theta / pi
    // (the trigonometry only when a texture reads it).
    si.dpdu = Vec3(-q.y, q.x, 0.f) * (2.f * kPi * s.radius);
    if (!(glm::dot(si.dpdu, si.dpdu) > 1e-20f)) si.dpdu = Vec3(1.f, 0.f, 0.f);
    if (s.needs_uv) {
      float phi = std::atan2(q.y, q.x);
      if (phi < 0.f) phi += 2.f * kPi;
      const float theta = safe_acos(q.z);
      si.uv = Vec2(phi * kInv2Pi, theta * kInvPi);
      si.dpdv = Vec3(q.z * std::cos(phi), q.z * std::sin(phi), -std::sin(theta)) * (kPi * s.radius);
    }
  } else {
    const glm::uvec3 tri = s.indices[prim];
    const float b1 = bu, b2 = bv, b0 = 1.f - b1 - b2;
    si.bary = Vec2(b1, b2);
    const Vec3 p0 = s.positions[tri.x], p1 = s.positions[tri.y], p2 = s.positions[tri.z];
    si.p = p0 * b0 + p1 * b1 + p2 * b2;
    const Vec3 e1 = p1 - p0, e2 = p2 - p0;
    si.ng = glm::normalize(glm::cross(e1, e2));
    if (!s.normals.empty()) {
      ns = s.normals[tri.x] * b0 + s.normals[tri.y] * b1 + s.normals[tri.z] * b2;
      const float l = glm::length(ns);
      ns = l > 0.f ? ns / l : si.ng;
    } else {
      ns = si.ng;
    }
    bool have_dp = false;
    if (!s.uvs.empty()) {
      const Vec2 uv0 = s.uvs[tri.x], uv1 = s.uvs[tri.y], uv2 = s.uvs[tri.z];
      si.uv = uv0 * b0 + uv1 * b1 + uv2 * b2;
      const Vec2 d1 = uv1 - uv0, d2 = uv2 - uv0;
      const float det = d1.x * d2.y - d1.y * d2.x;
      if (std::abs(det) > 1e-12f) {
        const float inv = 1.f / det;
        si.dpdu = (d2.y * e1 - d1.y * e2) * inv;
        si.dpdv = (-d2.x * e1 + d1.x * e2) * inv;
        have_dp = is_finite(si.dpdu) && is_finite(si.dpdv);
      }
    } else {
      si.uv = Vec2(b1, b2);
    }
    if (!have_dp) {
      si.dpdu = e1;
      si.dpdv = e2;
    }
  }
  if (s.flip_normals) {
    si.ng = -si.ng;
    ns = -ns;
  }
  si.sh = Frame::from_normal_tangent(ns, si.dpdu);
  return si;
}

bool Scene::occluded_to(const Vec3& p, const Vec3& ng, const Vec3& target) const {
  const Vec3 org = offset_ray_origin(p, ng, target - p);
  const Vec3 to_t = target - org;
  const float len = glm::length(to_t);
  if (!(len > 0.f)) return false;
  return occluded(org, to_t / len, 0.f, len * (1.f - 1e-4f));
}

bool Scene::occluded(const Vec3& o, const Vec3& d, float tmin, float tmax) const {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  RTCRay r;
  r.org_x = o.x; r.org_y = o.y; r.org_z = o.z;
  r.dir_x = d.x; r.dir_y = d.y; r.dir_z = d.z;
  r.tnear = tmin; r.tfar = tmax;
  r.mask = 0xffffffffu; r.flags = 0; r.time = 0.f;
  double t;
  const double inv_a = inv_len2(d);
  for (const DirectSphere& s : direct_spheres_)
    if (hit_sphere(s, o, d, inv_a, tmin, tmax, t)) return true;
  if (rtc_empty_) return false;
  rtcOccluded1(rtc_, &ctx, &r);
  return r.tfar < 0.f;
}

EmitterSample Scene::sample_emitter(const Vec3& ref, float u_sel, const Vec2& u) const {
  EmitterSample es;
  if (light_dist_.empty()) return es;
  const size_t k = light_dist_.sample(u_sel);
  const float psel = light_dist_.pmf(k);
  const int ei = light_list_[k];
  const Emitter& e = emitters[size_t(ei)];
  es.emitter = ei;
  switch (e.type) {
    case Emitter::Type::Area: {
      const Shape& s = shapes[size_t(e.shape)];
      Vec3 p, n;
      s.sample_position(u, p, n);
      const Vec3 d = p - ref;
      const float d2 = glm::dot(d, d);
      if (!(d2 > 0.f)) return es;
      es.dist = std::sqrt(d2);
      es.wi = d / es.dist;
      const float cos_l = -glm::dot(es.wi, n);
      if (cos_l <= 0.f) return es;  // one-sided emitter seen from behind
      es.p = p;
      es.value = e.value;
      es.pdf = psel * d2 / (cos_l * s.area);
      return es;
    }
    case Emitter::Type::Point:
    case Emitter::Type::Spot: {
      const Vec3 d = e.position - ref;
      const float d2 = glm::dot(d, d);
      if (!(d2 > 0.f)) return es;
      es.dist = std::sqrt(d2);
      es.wi = d / es.dist;
      es.p = e.position;
      float f = 1.f;
      if (e.type == Emitter::Type::Spot) f = e.spot_falloff(e.frame.to_local(-es.wi));
      es.value = e.value * (f / d2);
      es.pdf = psel;
      es.delta = true;
      return es;
    }
    case Emitter::Type::Directional:
      es.wi = -e.direction;
      es.value = e.value;
      es.pdf = psel;
      es.delta = true;
      return es;
    case Emitter::Type::Constant:
      es.wi = warp::square_to_uniform_sphere(u);
      es.value = e.value;
      es.pdf = psel * kInv4Pi;
      return es;
    case Emitter::Type::Envmap: {
      float pdf_uv;
      const Vec2 uv = e.env_dist.sample(u, pdf_uv);
      const float st = std::sin(uv.y * kPi);
      if (!(pdf_uv > 0.f) || !(st > 1e-7f)) return es;
      es.wi = e.env_dir(uv);
      es.value = e.env_lookup(uv) * e.scale;
      es.pdf = psel * pdf_uv / (2.f * kPi * kPi * st);
      return es;
    }
  }
  return es;
}

float Scene::pdf_emitter_hit(const Vec3& ref, const SurfaceInteraction& si) const {
  const Shape& s = shapes[size_t(si.shape)];
  if (s.emitter < 0) return 0.f;
  const int li = light_index_[size_t(s.emitter)];
  if (li < 0) return 0.f;
  const Vec3 d = si.p - ref;
  const float d2 = glm::dot(d, d);
  const float cos_l = std::abs(glm::dot(si.ng, d)) / std::sqrt(d2);
  if (!(cos_l > 0.f)) return 0.f;
  return light_dist_.pmf(size_t(li)) * d2 / (cos_l * s.area);
}

float Scene::pdf_emitter_escape(int e, const Vec3& d) const {
  const int li = light_index_[size_t(e)];
  if (li < 0) return 0.f;
  return light_dist_.pmf(size_t(li)) * emitters[size_t(e)].pdf_env(d);
}

Color Scene::emitted(const SurfaceInteraction& si) const {
  const Shape& s = shapes[size_t(si.shape)];
  if (s.emitter < 0) return Color(0.f);
  if (glm::dot(si.wi, si.ng) <= 0.f) return Color(0.f);
  return emitters[size_t(s.emitter)].value;
}

}  // namespace mpg
