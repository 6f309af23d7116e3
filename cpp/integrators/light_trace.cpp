#include "integrators/light_trace.h"

#include <algorithm>
#include <cmath>

namespace mpg {

namespace {
// A BSDF node whose every leaf is smooth or rough below the threshold, under
// normal maps or not (glossy mode's caster shapes; the walk's specular_node
// without its normal-map restriction).
bool glossy_reflector_node(const BSDFSet& b, int id, float thr) {
  if (id < 0) return false;
  const BSDF& n = b.nodes[size_t(id)];
  if (n.type == BSDFType::Conductor) return true;
  if (n.type == BSDFType::RoughConductor) return std::max(n.mf.ax, n.mf.ay) < thr;
  if (n.type == BSDFType::NormalMap) return glossy_reflector_node(b, n.nested, thr);
  return false;
}
bool glossy_caster_node(const BSDFSet& b, int id, float thr) {
  if (id < 0) return false;
  const BSDF& n = b.nodes[size_t(id)];
  if (ChainEstimator::chain_leaf(n, thr)) return true;
  // (two-sided: reflective sides only. BSDFSet::resolve picks the side by the
  // direction it is given, the camera's on the path tracer's side and the
  // light's on the photon's: one side for a reflection, two for a transmission)
  if (n.type == BSDFType::TwoSided)
    return glossy_reflector_node(b, n.front, thr) && glossy_reflector_node(b, n.back, thr);
  if (n.type == BSDFType::NormalMap) return glossy_caster_node(b, n.nested, thr);
  return false;
}
}  // namespace

LightTracer::LightTracer(const Scene& scene, const ChainEstimator& chains, int max_depth, bool through,
                         float photons_per_sample, bool area)
    : scene_(scene), chains_(&chains), rate_(photons_per_sample), area_(area) {
  if (!chains.active()) {
    why_ = "the scene runs no chain estimator";
    return;
  }
  // The camera's first hits: a depth-0 separator as the path tracer counts it.
  max_depth_ = uint32_t(max_depth);
  nmax_ = chains.max_chain_len(0, max_depth_);
  std::vector<char> casters(scene.shapes.size(), 0);
  for (size_t s = 0; s < scene.shapes.size(); ++s) casters[s] = chains.is_chain_shape(int(s)) ? 1 : 0;
  if (!init_common(casters)) return;
  // Camera-side chains of 1..mmax vertices (room for a light chain of one
  // vertex behind them: m + 1 + n + 1 segments <= max_depth)
  if (through && chains.sms_star_mode())
    mmax_cam_ = max_depth < 0 ? chains.max_chain() : std::min(chains.max_chain(), max_depth - 3);
  mmax_cam_ = std::max(mmax_cam_, 0);
  usable_ = true;
}

LightTracer::LightTracer(const Scene& scene, int max_depth, int nmax, float glossy_threshold,
                         float photons_per_sample, bool area)
    : scene_(scene), glossy_(true), glossy_threshold_(glossy_threshold), rate_(photons_per_sample), area_(area) {
  max_depth_ = uint32_t(max_depth);
  nmax_ = nmax;
  // the casters: as the chain estimator's shapes (not emitters; a glossy
  // caustic_receiver is a separator), normal maps allowed
  caster_shape_.assign(scene.shapes.size(), 0);
  for (size_t s = 0; s < scene.shapes.size(); ++s) {
    const Shape& sh = scene.shapes[s];
    if (sh.emitter < 0 && glossy_caster_node(scene.bsdfs, sh.bsdf, glossy_threshold) &&
        !(sh.caustic_receiver && !glossy_caster_node(scene.bsdfs, sh.bsdf, 0.f)))
      caster_shape_[s] = 1;
  }
  if (!init_common(caster_shape_)) return;
  usable_ = true;
}

bool LightTracer::caster_vertex(int shape, const BSDF& leaf) const {
  if (!glossy_) return chains_->is_chain_shape(shape) && chains_->is_chain_bsdf(leaf);
  if (shape < 0 || size_t(shape) >= caster_shape_.size() || !caster_shape_[size_t(shape)]) return false;
  return ChainEstimator::chain_leaf(leaf, glossy_threshold_);
}

bool LightTracer::init_common(const std::vector<char>& casters) {
  const Scene& scene = scene_;
  std::vector<float> w;
  for (size_t e = 0; e < scene.emitters.size(); ++e) {
    const Emitter& em = scene.emitters[e];
    // the estimator's chain lights (chain_estimator.cpp): delta positions,
    // and with area_ the area lights
    const bool kind = em.type == Emitter::Type::Point || em.type == Emitter::Type::Spot ||
                      (area_ && em.type == Emitter::Type::Area && em.shape >= 0);
    if (kind && em.power > 0.f && std::isfinite(em.power)) {
      lights_.push_back(int(e));
      w.push_back(em.power);
    }
  }
  if (lights_.empty()) {
    why_ = area_ ? "the scene has no point, spot or area light" : "the scene has no point or spot light";
    return false;
  }
  light_dist_.build(w);
  traced_.assign(scene.emitters.size(), 0);
  for (int e : lights_) traced_[size_t(e)] = 1;
  if (nmax_ < 1) {
    why_ = "max_depth leaves no room for a chain after the camera's first hit";
    return false;
  }
  if (chains_ && !chains_->chain_shapes_smooth()) {
    // A glossy chain vertex would need the adjoint of its rough BSDF and the
    // estimator's offset normals; not done: the estimator keeps those paths.
    // (Glossy mode traces such vertices where no estimator runs.)
    why_ = "a chain shape is glossy or normal-mapped (only smooth glass and mirrors are light traced)";
    return false;
  }
  const Camera& cam = scene.camera;
  if (cam.filter.type != FilterSampler::Type::Box || std::abs(cam.filter.radius - 0.5f) > 1e-6f) {
    why_ = "the film's reconstruction filter is not a box of one pixel";
    return false;
  }
  // Bounding sphere of the chain shapes: photons are aimed into its cone.
  Vec3 lo(kInf), hi(-kInf);
  for (size_t s = 0; s < scene.shapes.size(); ++s)
    if (casters[s]) scene.shapes[s].grow_bounds(lo, hi);
  if (!(lo.x <= hi.x)) {
    why_ = glossy_ ? "no shape is a caster (smooth, or rough below the glossy threshold)" : "no chain shape";
    return false;
  }
  bound_c_ = 0.5f * (lo + hi);
  // (a margin for float rounding of the hits against the box)
  bound_r_ = 0.5 * glm::length(DVec3(hi - lo)) * (1.0 + 1e-4) + 1e-4 * std::max(1.f, max_comp(glm::abs(bound_c_)));
  to_local_ = glm::inverse(cam.to_world);
  cam_o_ = Vec3(cam.to_world * Vec4(0.f, 0.f, 0.f, 1.f));
  cam_fwd_ = glm::normalize(Vec3(cam.to_world * Vec4(0.f, 0.f, 1.f, 0.f)));
  const double a_pix = (2.0 * cam.tan_half_x / cam.width) * (2.0 * cam.tan_half_y / cam.height);
  if (!(a_pix > 0.0)) {
    why_ = "the camera's field of view is empty";
    return false;
  }
  inv_a_pix_ = 1.0 / a_pix;
  return true;
}

void LightTracer::trace(PCG32& rng, Stats& st, std::vector<LightSplat>& out) const {
  st.lt_photons++;
  float u = rng.next_float();
  const size_t k = light_dist_.sample(u);
  const Emitter& em = scene_.emitters[size_t(lights_[k])];
  const double psel = light_dist_.pmf(k);
  // The emission point: the point light's position, or uniform by area on the
  // area light's shape (density 1 / A), emitting Le toward its geometric
  // normal's side (Scene::emitted)
  const bool is_area = em.type == Emitter::Type::Area;
  Vec3 xL = em.position, nL(0.f);
  double pdf_pos = 1.0;
  if (is_area) {
    const Shape& ls = scene_.shapes[size_t(em.shape)];
    ls.sample_position(Vec2(rng.next_float(), rng.next_float()), xL, nL);
    if (!(ls.area > 0.f)) return;
    pdf_pos = 1.0 / double(ls.area);
  }
  // Direction: uniform in the cone around the chain shapes' bounding sphere
  // (uniform on the sphere of directions from inside it). A path whose first
  // segment leaves the cone meets no chain shape first, so it is not one of
  // this tracer's paths: the cone loses nothing. In double: a far light's cone
  // has 1 - cos_max ~ 1e-9.
  const Vec2 u2(rng.next_float(), rng.next_float());
  const DVec3 to_c = DVec3(bound_c_) - DVec3(xL);
  const double dist_c = glm::length(to_c);
  double one_minus_cos_max = 2.0;   // the whole sphere
  if (dist_c > bound_r_) {
    const double s2 = (bound_r_ / dist_c) * (bound_r_ / dist_c);
    one_minus_cos_max = s2 / (1.0 + std::sqrt(std::max(0.0, 1.0 - s2)));
  }
  const double omc = double(u2.x) * one_minus_cos_max;   // 1 - cos(theta), uniform
  const double cos_t = 1.0 - omc;
  const double sin_t = std::sqrt(std::max(0.0, omc * (2.0 - omc)));
  const double phi = 2.0 * M_PI * double(u2.y);
  const Frame fr(dist_c > bound_r_ ? Vec3(to_c / dist_c) : Vec3(0.f, 0.f, 1.f));
  Vec3 d = glm::normalize(fr.to_world(Vec3(float(sin_t * std::cos(phi)), float(sin_t * std::sin(phi)), float(cos_t))));
  const double pdf_dir = 1.0 / (2.0 * M_PI * one_minus_cos_max);
  // Point/spot: intensity I. Area: radiance times the projected area the
  // position's density stands for, Le |cos(n_L, d)| / p_A (one-sided).
  Color I = em.value;
  if (em.type == Emitter::Type::Spot) I *= em.spot_falloff(em.frame.to_local(d));
  if (is_area) {
    const float cl = glm::dot(nL, d);
    if (!(cl > 0.f)) return;
    I *= float(double(cl) / pdf_pos);
  }
  if (is_black(I)) return;
  Color flux = I * float(1.0 / (psel * pdf_dir));
  // Trace through chain vertices (the estimator's shapes and smooth BSDFs),
  // R/T by Fresnel as the BSDF samples them; in glossy mode through the
  // casters, any lobe their BSDF samples.
  Vec3 o = xL;
  Vec3 prev_ng = nL;   // (an area light's ray leaves from an offset origin)
  int n = 0;
  thread_local std::string letters;   // light -> x_D order (n <= nmax_ <= max_chain)
  letters.clear();
  for (;;) {
    const Vec3 org = (n == 0 && !is_area) ? o : offset_ray_origin(o, prev_ng, d);
    st.lt_rays++;
    SurfaceInteraction si = scene_.intersect(org, d, 0.f, kInf);
    if (!si.valid) return;
    const Shape& shape = scene_.shapes[size_t(si.shape)];
    const BSDFContext ctx = scene_.bsdfs.resolve(shape.bsdf, si);
    if (!ctx.leaf) return;
    const bool chain_vertex = caster_vertex(si.shape, *ctx.leaf);
    if (!chain_vertex) {
      // not a separator (a delta surface off the chain shapes), or the
      // light's direct illumination (next-event estimation's): none of ours.
      // (Glossy mode leaves the delta test to the splat, which resolves the
      // BSDF toward the camera as the path tracer does: a two-sided one with
      // a delta side resolves its side by the direction given.)
      if ((!glossy_ && ctx.leaf->is_delta()) || n == 0) return;
      // only the chains the estimator would own at the camera's first hit
      // (sms: its one type), the letters in x_D -> x_L order
      std::string tau(letters.rbegin(), letters.rend());
      const size_t before = out.size();
      if (glossy_ || chains_->owns(0, max_depth_, tau)) connect(si, shape, flux, out, st);   // x_D seen directly
      // ... or through glass (not an area light's photon: its splat would carry
      // the camera-side chain's |d omega_c / dA_D|, unbounded at the folds of
      // what the camera sees in the glass, where the area light's photons land
      // spread out; measured, docs/design-notes.md)
      if (mmax_cam_ > 0 && !is_area) connect_chain(si, shape, flux, tau, rng, out, st);
      // one photon, one sample of each pixel: two splats in one pixel are one value
      if (out.size() == before + 2 && out[before].pixel == out[before + 1].pixel) {
        out[before].value += out[before + 1].value;
        out.pop_back();
      }
      return;
    }
    if (n == nmax_) return;
    Vec3 wo;
    const float u1 = rng.next_float();
    const Vec2 v2(rng.next_float(), rng.next_float());
    const Vec3 wl = si.wi;   // toward the light side
    BSDFSample bs;
    if (glossy_) {
      // Under a normal map BSDFSet rejects a direction between the base and
      // the perturbed tangent planes on its second argument only: the path
      // tracer's light side, here wl. So the photon checks wl and samples
      // the leaf without the check on the camera side, as the path tracer
      // accepts it there.
      if (ctx.perturbed && ctx.base.to_local(wl).z * ctx.frame.to_local(wl).z <= 0.f) return;
      bs = scene_.bsdfs.sample_local(*ctx.leaf, ctx.uv, ctx.frame.to_local(wl), u1, v2);
      if (bs.pdf > 0.f) wo = ctx.frame.to_world(bs.wo);
    } else {
      bs = scene_.bsdfs.sample(ctx, wl, u1, v2, wo);
    }
    if (!(bs.pdf > 0.f) || is_black(bs.weight) || (!bs.delta && !glossy_)) return;
    // flux weight: radiance mode's (eta_i / eta_t)^2 of a refraction undone
    // (bs.eta = eta_t / eta_i), and the adjoint's shading-normal correction
    // |cos(n_s, w_l) cos(n_g, w_o)| / |cos(n_g, w_l) cos(n_s, w_o)| (1 without a normal map)
    Color wgt = bs.weight;
    if (bs.transmission) wgt *= bs.eta * bs.eta;
    const float num = std::abs(glm::dot(ctx.frame.n, wl) * glm::dot(si.ng, wo));
    const float den = std::abs(glm::dot(si.ng, wl) * glm::dot(ctx.frame.n, wo));
    if (!(den > 0.f)) return;
    flux *= wgt * (num / den);
    letters.push_back(bs.transmission ? 'T' : 'R');
    ++n;
    o = si.p;
    prev_ng = si.ng;
    d = wo;
  }
}

void LightTracer::connect(const SurfaceInteraction& si, const Shape& shape, const Color& flux,
                          std::vector<LightSplat>& out, Stats& st) const {
  const Vec3 to_cam = cam_o_ - si.p;
  const float dist = glm::length(to_cam);
  if (!(dist > 0.f)) return;
  const Vec3 wc = to_cam / dist;
  uint32_t pixel = 0;
  float cos_c = 0.f, t_near = 0.f;
  if (!project(si.p, pixel, cos_c, t_near)) return;
  // G = |d omega_c / dA_D| = |cos(n_g, w_c)| / d^2
  const double G = std::abs(double(glm::dot(si.ng, wc))) / (double(dist) * double(dist));
  splat(si, shape, wc, si.p, si.ng, t_near, Color(float(G)), flux, pixel, cos_c, out, st);
}

bool LightTracer::splat(SurfaceInteraction si, const Shape& shape, const Vec3& w_out, const Vec3& from,
                        const Vec3& from_ng, float t_near, const Color& G, const Color& flux, uint32_t pixel,
                        float cos_c, std::vector<LightSplat>& out, Stats& st) const {
  const Vec3 wl = si.wi;   // toward the photon's last chain vertex
  // the BSDF as the camera path evaluates it at x_D: wi toward the camera side
  si.wi = w_out;
  const BSDFContext ctx = scene_.bsdfs.resolve(shape.bsdf, si);
  if (!ctx.leaf) return false;
  const Color f = scene_.bsdfs.eval(ctx, w_out, wl);   // f_s(w_out, w_l) |cos(n_s, w_l)|
  if (is_black(f)) return false;
  const double cos_l = std::abs(double(glm::dot(si.ng, wl)));
  if (!(cos_l > 0.0)) return false;
  // visible as the camera ray sees it: that ray starts at the near plane
  // (world distance t_near from the pinhole), so what lies nearer does not occlude
  st.shadow_rays++;
  const Vec3 wc = glm::normalize(cam_o_ - from);
  const Vec3 org = offset_ray_origin(from, from_ng, wc);
  if (scene_.occluded(org, wc, 0.f, (glm::length(cam_o_ - org) - t_near) * (1.f - 1e-4f))) return false;
  const double cc = double(cos_c);
  const double g = inv_a_pix_ / (cos_l * cc * cc * cc);
  Color v(0.f);
  for (int c = 0; c < 3; ++c) v[c] = float(double(flux[c]) * double(f[c]) * double(G[c]) * g);
  if (!(std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z)) || v.x < 0.f || v.y < 0.f || v.z < 0.f) {
    st.lt_rejected++;
    return false;
  }
  if (is_black(v)) return false;
  st.lt_splats++;
  out.push_back(LightSplat{pixel, v});
  return true;
}

bool LightTracer::project(const Vec3& p, uint32_t& pixel, float& cos_c, float& t_near) const {
  const Camera& cam = scene_.camera;
  // film position (generate_ray inverted): local x left, y up, z forward
  const Vec4 q = to_local_ * Vec4(p, 1.f);
  Vec2 film;
  if (!cam.film_position(q, film)) return false;
  // the camera ray's clip distances are along the optical axis, in the
  // camera's local units (Camera::generate_ray)
  if (q.z < cam.near_clip || q.z > cam.far_clip) return false;
  const float fx = film.x, fy = film.y;
  if (!(fx >= 0.f && fy >= 0.f)) return false;
  const int px = int(std::floor(fx)) - cam.crop_x, py = int(std::floor(fy)) - cam.crop_y;
  if (px < 0 || py < 0 || px >= cam.crop_w || py >= cam.crop_h) return false;
  const Vec3 to_cam = cam_o_ - p;
  const float dist = glm::length(to_cam);
  cos_c = glm::dot(cam_fwd_, -to_cam / dist);
  if (!(cos_c > 0.f)) return false;
  // the camera ray starts at the near plane: world distance dist * near / q.z
  // from the pinhole; what lies nearer does not occlude
  t_near = dist * cam.near_clip / q.z;
  pixel = uint32_t(py) * uint32_t(cam.crop_w) + uint32_t(px);
  return true;
}

void LightTracer::connect_chain(const SurfaceInteraction& si, const Shape& shape, const Color& flux,
                                const std::string& tau_l, PCG32& rng, std::vector<LightSplat>& out,
                                Stats& st) const {
  ManifoldChain chain;
  Color w(0.f);
  st.lt_chain_tries++;
  if (!chains_->connect_point(DVec3(si.p), DVec3(si.ng), DVec3(cam_o_), mmax_cam_, rng, st, chain, w)) return;
  // the photon's light chain must be one the estimator owns behind m camera-side vertices
  if (!chains_->owns(uint32_t(chain.v.size()), max_depth_, tau_l)) return;
  const Vec3 last = Vec3(chain.v.back().p);
  uint32_t pixel = 0;
  float cos_c = 0.f, t_near = 0.f;
  if (!project(last, pixel, cos_c, t_near)) return;
  // x_D's BSDF toward the chain's first vertex; w = kappa G_c K / P(m) with
  // G_c = |d omega_c / dA_D| in place of the direct view's |cos(n_g, w_c)| / d^2
  const Vec3 wD = glm::normalize(Vec3(chain.v.front().p) - si.p);
  if (splat(si, shape, wD, last, Vec3(chain.v.back().ng), t_near, w, flux, pixel, cos_c, out, st))
    st.lt_chain_splats++;
}

}  // namespace mpg
