#include "manifold/chain_estimator.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <thread>

#include "core/warp.h"
#include "scene/fresnel.h"

namespace mpg {

static_assert(size_t(WalkFailure::Count) == std::tuple_size<decltype(Stats::walk_failures)>::value,
              "Stats::walk_failures must have one entry per WalkFailure");

namespace {
using Clock = std::chrono::steady_clock;
uint64_t ns_since(Clock::time_point t0) {
  return uint64_t(std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now() - t0).count());
}
// The guide's timer (stat guide_ns) times one call in kGuideTimeEvery per
// thread and counts it that many times: two clock reads (~47 ns here) cost
// about as much as the leaf query they would time, and on pool (millions of
// cheap calls) timing each one was a quarter of the reported overhead.
constexpr uint32_t kGuideTimeEvery = 8;
thread_local uint32_t guide_tick = 0;
inline bool time_guide_call() { return guide_tick++ % kGuideTimeEvery == 0; }
// A timed interval also holds the clock's own cost, from the first read's
// sample to the second's: the median of back-to-back pairs of reads, measured
// once per process. A timed guide call adds it to Stats::guide_clock_ns, which
// the reported guide_ns leaves out (stats.h). The pairs run hot in cache, so
// the floor is the clock's least cost and what is left out errs low.
uint64_t clock_floor_ns() {
  static const uint64_t floor = [] {
    std::array<uint64_t, 101> d{};
    for (auto& x : d) {
      const auto a = Clock::now();
      x = ns_since(a);
    }
    std::nth_element(d.begin(), d.begin() + 50, d.end());
    return d[50];
  }();
  return floor;
}
inline void add_guide_time(Stats& st, Clock::time_point t0) {
  st.guide_ns += kGuideTimeEvery * ns_since(t0);
  st.guide_clock_ns += kGuideTimeEvery * clock_floor_ns();
}
DVec3 to_d(const Vec3& v) { return DVec3(v.x, v.y, v.z); }
Vec3 to_f(const DVec3& v) { return Vec3(float(v.x), float(v.y), float(v.z)); }

// A BSDF node that the walk treats as one specular (or glossy chain) interface.
bool specular_node(const BSDFSet& b, int id, float glossy_threshold) {
  if (id < 0) return false;
  const BSDF& n = b.nodes[size_t(id)];
  if (n.type == BSDFType::Dielectric || n.type == BSDFType::Conductor) return true;
  if ((n.type == BSDFType::RoughDielectric || n.type == BSDFType::RoughConductor) &&
      std::max(n.mf.ax, n.mf.ay) < glossy_threshold)
    return true;
  if (n.type == BSDFType::TwoSided)
    return specular_node(b, n.front, glossy_threshold) && specular_node(b, n.back, glossy_threshold);
  if (n.type == BSDFType::NormalMap)  // one level of tangent-space normal map over a smooth interface
    return b.nodes[size_t(n.nested)].type == BSDFType::Dielectric ||
           b.nodes[size_t(n.nested)].type == BSDFType::Conductor;
  return false;
}
// A normal map at the node or under its two sides (the light tracer declines those).
bool has_normal_map(const BSDFSet& b, int id) {
  if (id < 0) return false;
  const BSDF& n = b.nodes[size_t(id)];
  if (n.type == BSDFType::NormalMap) return true;
  if (n.type == BSDFType::TwoSided) return has_normal_map(b, n.front) || has_normal_map(b, n.back);
  return false;
}
}  // namespace

ChainEstimator::ChainEstimator(const Scene& scene, ChainParams p)
    : scene_(scene), p_(p), walk_(scene, p.walk) {
  specular_shape_.assign(scene.shapes.size(), 0);
  std::vector<float> areas;
  for (size_t i = 0; i < scene.shapes.size(); ++i) {
    // A glossy shape the scene marks caustic_receiver is a separator even below
    // the threshold (a glossy floor receives the caustic; SMS and MPG run their
    // estimators on receivers). A smooth one -- a chain node at threshold 0 --
    // stays a chain shape: as a delta surface it would be no separator either,
    // and a point light's caustic through it would be lost.
    if (specular_node(scene.bsdfs, scene.shapes[i].bsdf, p.walk.glossy_threshold) && scene.shapes[i].emitter < 0 &&
        !(scene.shapes[i].caustic_receiver && !specular_node(scene.bsdfs, scene.shapes[i].bsdf, 0.f))) {
      specular_shape_[i] = 1;
      if (!specular_node(scene.bsdfs, scene.shapes[i].bsdf, 0.f) || has_normal_map(scene.bsdfs, scene.shapes[i].bsdf))
        chain_shapes_smooth_ = false;
      seed_shapes_.push_back(int(i));
      areas.push_back(scene.shapes[i].area);
    }
  }
  seed_dist_.build(areas);
  std::vector<float> w;
  for (size_t e = 0; e < scene.emitters.size(); ++e) {
    const Emitter& em = scene.emitters[e];
    const bool chain = em.type == Emitter::Type::Area || em.type == Emitter::Type::Point ||
                       em.type == Emitter::Type::Spot;
    if (chain && em.power > 0.f && std::isfinite(em.power)) {
      chain_lights_.push_back(int(e));
      w.push_back(em.power);
      if (em.type != Emitter::Type::Area) has_delta_lights_ = true;
    }
  }
  light_dist_.build(w);
  light_index_.assign(scene.emitters.size(), -1);
  for (size_t k = 0; k < chain_lights_.size(); ++k) light_index_[size_t(chain_lights_[k])] = int(k);
  // The guided trace's leaf is the one of (x_D, the light's centroid): the mean
  // of a 16 x 16 grid of its area samples (any fixed point of the light would do).
  light_centre_.assign(chain_lights_.size(), Vec3(0.f));
  for (size_t k = 0; k < chain_lights_.size(); ++k) {
    const Emitter& em = scene.emitters[size_t(chain_lights_[k])];
    if (em.type != Emitter::Type::Area) {
      light_centre_[k] = em.position;
      continue;
    }
    DVec3 c(0.0);
    for (int i = 0; i < 16; ++i)
      for (int j = 0; j < 16; ++j) {
        Vec3 q, nq;
        scene.shapes[size_t(em.shape)].sample_position(Vec2((float(i) + 0.5f) / 16.f, (float(j) + 0.5f) / 16.f), q, nq);
        c += to_d(q);
      }
    light_centre_[k] = to_f(c / 256.0);
  }
  // Effects follow the scene: no specular caster or no chain emitter, no work.
  active_ = !seed_dist_.empty() && !light_dist_.empty();
  if (p_.mode == ChainParams::Mode::Sms && p_.tau.empty()) active_ = false;
}

int ChainEstimator::max_len(uint32_t depth, uint32_t max_depth) const {
  int cap = p_.mode == ChainParams::Mode::Sms ? int(p_.tau.size()) : p_.max_chain;
  if (max_depth != uint32_t(-1)) {
    const long room = long(max_depth) - long(depth) - 2;
    cap = int(std::min<long>(cap, room));
  }
  return cap;
}

bool ChainEstimator::owns(uint32_t depth, uint32_t max_depth, const std::string& tau) const {
  if (!active_ || tau.empty()) return false;
  const int n = int(tau.size());
  if (n > max_len(depth, max_depth)) return false;
  if (p_.mode == ChainParams::Mode::Sms) return tau == p_.tau;
  return true;
}

double ChainEstimator::pmf_n(int n, int nmax) const {
  if (p_.mode == ChainParams::Mode::Sms) return 1.0;
  const double q = p_.continuation;
  if (n < 1 || n > nmax) return 0.0;
  return n < nmax ? std::pow(q, n - 1) * (1.0 - q) : std::pow(q, n - 1);
}

int ChainEstimator::sample_n(float u, int nmax) const {
  if (p_.mode == ChainParams::Mode::Sms) return int(p_.tau.size());
  double c = 0.0;
  for (int n = 1; n < nmax; ++n) {
    c += pmf_n(n, nmax);
    if (u < c) return n;
  }
  return nmax;
}

double ChainEstimator::pmf_n_mix(int n, int nmax, const ChainDistribution* d, double mass) const {
  const double p0 = pmf_n(n, nmax);
  if (!d || !p_.guide_n || !(mass > 0.0)) return p0;
  const double pe = n <= nmax ? double(d->pmf_n(n)) / mass : 0.0;
  return (1.0 - p_.guide_fraction) * p0 + p_.guide_fraction * pe;  // MPG Eq. 13
}

double ChainEstimator::area_light_pdf(size_t k) const {
  const Emitter& e = scene_.emitters[size_t(chain_lights_[k])];
  return light_dist_.pmf(k) / double(scene_.shapes[size_t(e.shape)].area);
}

bool ChainEstimator::sample_light(PCG32& rng, LightPoint& lp) const {
  float u = rng.next_float();
  const size_t k = light_dist_.sample(u);
  const Emitter& e = scene_.emitters[size_t(chain_lights_[k])];
  const double psel = light_dist_.pmf(k);
  lp.emitter = chain_lights_[k];
  if (e.type == Emitter::Type::Area) {
    const Shape& s = scene_.shapes[size_t(e.shape)];
    Vec3 p, n;
    s.sample_position(Vec2(rng.next_float(), rng.next_float()), p, n);
    lp.p = to_d(p);
    lp.n = to_d(n);
    lp.value = e.value;
    lp.pdf = area_light_pdf(k);  // the path tracer's side uses the same (pt_densities)
    lp.point = false;
  } else {
    lp.p = to_d(e.position);
    lp.n = DVec3(0.0, 1.0, 0.0);  // any: only used for the (unused) light chart
    lp.value = e.value;
    lp.pdf = psel;
    lp.point = true;
  }
  return lp.pdf > 0.0;
}

namespace {
// A walk's work (Stats), and its work under each line-search limit (TrialTally).
void count_walk(const WalkResult& r, int n, Stats& st, TrialTally* tally) {
  st.walk_steps += uint64_t(n) * uint64_t(r.iterations);
  st.walk_reprojections += uint64_t(r.reprojections);
  st.walk_off_surface += uint64_t(r.off_surface);
  if (!tally) return;
  tally->later_rejections = r.later_rejections;
  for (int h = 0; h < kHalvingSlots; ++h) tally->steps[size_t(h)] += uint32_t(n * r.limited_tries[size_t(h)]);
}
void count_seed(int n, TrialTally* tally) {
  if (tally)
    for (auto& s : tally->steps) s += uint32_t(n);
}
}  // namespace

bool ChainEstimator::initial_seed_dir(const DVec3& xD, PCG32& rng, DVec3& dir) const {
  // x_1 uniform by area on the specular shapes; the seed direction aims at it.
  float u = rng.next_float();
  const size_t k = seed_dist_.sample(u);
  Vec3 p1, n1;
  scene_.shapes[size_t(seed_shapes_[k])].sample_position(Vec2(rng.next_float(), rng.next_float()), p1, n1);
  dir = to_d(p1) - xD;
  return glm::length(dir) > 0.0;
}

bool ChainEstimator::trace_fresnel_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir, int n,
                                        const std::vector<Vec2>& offsets, PCG32& rng, ManifoldChain& chain,
                                        std::string& tau, Stats& st, const std::string* want_tau) const {
  // Trace n vertices choosing R/T at dielectrics by their Fresnel reflectance.
  chain.xD = xD;
  chain.nD = nD;
  chain.v.clear();
  tau.clear();
  DVec3 o = xD, on = nD, d = glm::normalize(dir);
  for (int i = 0; i < n; ++i) {
    const Vec3 of = offset_ray_origin(to_f(o), to_f(on), to_f(d));
    const SurfaceInteraction si = scene_.intersect(of, to_f(d), 0.f, kInf);
    if (!si.valid || !is_chain_shape(si.shape)) {
      st.walk_failures[size_t(WalkFailure::LeftSurface)]++;
      return false;
    }
    ManifoldVertex v;
    if (!walk_.make_vertex(si, true, v, &offsets[size_t(i)])) {
      st.walk_failures[size_t(WalkFailure::NotSpecular)]++;
      return false;
    }
    const DVec3 wi = -d;
    const double ci = glm::dot(wi, v.n);
    bool reflect = true;
    if (v.dielectric) {
      const float F = fresnel_dielectric(float(ci), float(v.eta)).F;
      reflect = rng.next_float() < F;
    }
    v.reflect = reflect;
    if (want_tau && size_t(i) < want_tau->size() && (reflect ? 'R' : 'T') != (*want_tau)[size_t(i)]) {
      st.trials_tau_cut++;  // cannot hit
      return false;
    }
    if (!ManifoldWalk::scatter(wi, v.n, v.eta, reflect, d)) {
      st.walk_failures[size_t(WalkFailure::TotalInternalReflection)]++;
      return false;
    }
    o = v.p;
    on = v.ng;
    tau.push_back(reflect ? 'R' : 'T');
    chain.v.push_back(v);
  }
  return true;
}

bool ChainEstimator::trial(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
                           const std::vector<Vec2>& offsets, const ChainDistribution* guide,
                           PCG32& rng, ManifoldChain& chain, std::string& tau, Stats& st,
                           TrialTally* tally, const std::string* want_tau) const {
  if (tally) *tally = TrialTally{};
  // (both ablation switches off: the callers pass no guide; guarded here too,
  // ahead of any random number, so a guide with nothing to guide is unused)
  if (guide && (p_.guide_tau || p_.guide_dir) && rng.next_float() < p_.guide_fraction) {
    // Learned seed (MPG Sec. 5.5): tau ~ P_e(tau | n), omega_D ~ the vMF mixture of
    // (n, tau); one-sample MIS with the initial distribution below (Eq. 13).
    // The ablations of supplemental Fig. 3 switch one of the two off:
    // guide_tau off: omega_D from the leaf's mixture over every tau of n (the
    // type drawn and forgotten), the letters by Fresnel along the seed as the
    // initial law draws them; guide_dir off: tau ~ P_e(tau | n), omega_D toward
    // x_1 uniform by area on the specular shapes, the seed traced with those
    // letters. The Bernoulli trials repeat this same procedure, so 1/P stays
    // the procedure's own (Eq. 15) whichever parts it guides.
    st.guided_trials++;
    const bool timed = time_guide_call();
    const auto tg = timed ? Clock::now() : Clock::time_point{};
    Vec3 dir(0.f);
    const float ut = rng.next_float();
    const int type = guide->sample_type(n, ut);
    bool ok = type >= 0;
    if (p_.guide_dir) {
      const double ul = rng.next_double();  // the lobe: alias bin and the fraction within it
      const Vec2 u(rng.next_float(), rng.next_float());
      ok = ok && guide->sample_dir_of(type, ul, u, Vec3(xD), dir);
    }
    if (timed) add_guide_time(st, tg);
    if (!ok) return false;
    chain.xL = lp.p;
    chain.nL = lp.n;
    if (p_.guide_tau) {
      const uint16_t bits = guide->type_tau(type);
      tau.assign(size_t(n), 'T');
      for (int i = 0; i < n; ++i)
        if (bits & (1u << i)) tau[size_t(i)] = 'R';
      if (want_tau && tau != *want_tau) {  // cannot hit: no seed traced, no walk
        st.trials_tau_cut++;
        return false;
      }
      DVec3 d = to_d(dir);
      if (!p_.guide_dir && !initial_seed_dir(xD, rng, d)) return false;
      // A trial's work in vertex steps (a traced or reprojected vertex: a ray and
      // a chart), deterministic unlike chain_ns: mpg.chain_rates' cost model. The
      // traced seed counts whether it fails or not, then each accepted Newton
      // iteration (the line search's rejected tries are not counted: see
      // walk_reprojections and design-notes, "Step control").
      st.walk_steps += uint64_t(n);
      count_seed(n, tally);
      if (!trace_lettered_seed(xD, nD, d, tau, offsets, chain, st)) return false;
    } else {
      st.walk_steps += uint64_t(n);  // the traced seed
      count_seed(n, tally);
      if (!trace_fresnel_seed(xD, nD, to_d(dir), n, offsets, rng, chain, tau, st, want_tau)) return false;
    }
    return solve_seed(chain, n, st, tally);
  }
  DVec3 dir;
  if (!initial_seed_dir(xD, rng, dir)) return false;
  chain.xL = lp.p;
  chain.nL = lp.n;
  st.walk_steps += uint64_t(n);  // the traced seed
  count_seed(n, tally);
  bool seeded;
  if (p_.mode == ChainParams::Mode::Sms) {
    tau = p_.tau;
    seeded = trace_lettered_seed(xD, nD, dir, tau, offsets, chain, st);
  } else {
    seeded = trace_fresnel_seed(xD, nD, dir, n, offsets, rng, chain, tau, st, want_tau);
  }
  return seeded && solve_seed(chain, n, st, tally);
}

bool ChainEstimator::trace_lettered_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir,
                                         const std::string& tau, const std::vector<Vec2>& offsets,
                                         ManifoldChain& chain, Stats& st) const {
  WalkFailure why = WalkFailure::None;
  if (!walk_.trace_seed(xD, nD, dir, tau, chain, why, &offsets)) {
    st.walk_failures[size_t(why)]++;
    return false;
  }
  if (!on_chain_shapes(chain)) {
    st.walk_failures[size_t(WalkFailure::LeftSurface)]++;
    return false;
  }
  return true;
}

bool ChainEstimator::solve_seed(ManifoldChain& chain, int n, Stats& st, TrialTally* tally) const {
  const WalkResult r = walk_.solve(chain);
  count_walk(r, n, st, tally);
  if (!r.converged) {
    st.walk_failures[size_t(r.failure)]++;
    return false;
  }
  return true;
}

// Vertex i of a chain as a hit seen from the previous vertex (for resolving its BSDF).
static SurfaceInteraction vertex_interaction(const ManifoldChain& c, size_t i) {
  const ManifoldVertex& v = c.v[i];
  const DVec3 xp = i == 0 ? c.xD : c.v[i - 1].p;
  SurfaceInteraction si;
  si.valid = true;
  si.p = to_f(v.p);
  si.ng = to_f(v.ng);
  si.sh = Frame(to_f(v.n));
  si.uv = v.uv;
  si.wi = to_f(glm::normalize(xp - v.p));
  si.shape = v.shape;
  return si;
}

Color ChainEstimator::kappa(const ManifoldChain& c, const std::string& tau, bool flux, double* eta2) const {
  // Product of the specular lobes' weights seen from x_D toward x_L, with the
  // path tracer's conventions (Fresnel, textures, 1/eta^2 radiance scaling).
  // flux (a point or spot light): without the radiance scaling. G is then the
  // solid angle at the light per unit area at x_D, |d omega_L / dA_D|, and a
  // point light's intensity I is flux per solid angle where it sits: the
  // irradiance is E = T I |d omega_L / dA_D| with T the lobes' plain weights
  // (flux is conserved through an interface; the radiance's (eta_D / eta_L)^2
  // is undone by the etendue, eta^2 cos d omega dA invariant). The two agree
  // when x_D and the light sit in the same medium (the factors cancel); a
  // light inside glass over a floor outside differs by eta^2 (test_light_trace).
  Color k(1.f);
  if (eta2) *eta2 = 1.0;
  const size_t n = c.v.size();
  for (size_t i = 0; i < n; ++i) {
    const ManifoldVertex& v = c.v[i];
    const SurfaceInteraction si = vertex_interaction(c, i);
    const BSDFContext ctx = scene_.bsdfs.resolve(scene_.shapes[size_t(v.shape)].bsdf, si);
    if (!ctx.leaf) return Color(0.f);
    const float ci = glm::dot(si.wi, ctx.frame.n);
    const BSDF& b = *ctx.leaf;
    if (v.mf) {
      // Glossy vertex as a smooth one with normal m, weighted by the rest of the
      // microfacet BSDF over the offset's density D(m) cos(theta_m):
      // f |cos_o| d omega_o = lobe(w_i . m) G |w_i . m| / |cos_i| D(m) d omega_m
      // (Walter et al. 2007, Eqs. 20-21 with their Jacobians 14 and 17).
      const DVec3 xn = i + 1 == n ? c.xL : c.v[i + 1].p;
      const Vec3 wi = si.wi, wo = to_f(glm::normalize(xn - v.p));
      const Vec3 m = to_f(v.n);
      // the frame the offset was drawn in (s along e1), with the shading normal
      ManifoldVertex base = v;
      base.mf = nullptr;
      const ManifoldVertex b0 = ManifoldWalk::moved(base, 0.0, 0.0);
      const Frame fr = Frame::from_normal_tangent(to_f(b0.n), to_f(v.e1));
      const Vec3 wil = fr.to_local(wi), wol = fr.to_local(wo), ml = fr.to_local(m);
      const float cos_i = std::abs(wil.z), cos_m = ml.z;
      if (!(cos_i > 0.f) || !(cos_m > 0.f)) return Color(0.f);
      const float wim = glm::dot(wi, m);
      const float G = v.mf->G(wil, wol, ml);
      Color lobe;
      if (b.type == BSDFType::RoughConductor) {
        if (ci <= 0.f || tau[i] != 'R') return Color(0.f);
        lobe = scene_.bsdfs.tex(b.specular_reflectance, v.uv) * fresnel_conductor(std::abs(wim), b.eta_c, b.k_c);
      } else {
        const DielectricFresnel f = fresnel_dielectric(wim, b.eta);
        if (eta2 && tau[i] != 'R') *eta2 *= double(f.eta_ti) * double(f.eta_ti);
        lobe = tau[i] == 'R' ? scene_.bsdfs.tex(b.specular_reflectance, v.uv) * f.F
                             : scene_.bsdfs.tex(b.specular_transmittance, v.uv) *
                                   (flux ? (1.f - f.F) : (1.f - f.F) * f.eta_ti * f.eta_ti);
      }
      k *= lobe * (G * std::abs(wim) / (cos_i * cos_m));
      continue;
    }
    if (b.type == BSDFType::Conductor) {
      if (ci <= 0.f || tau[i] != 'R') return Color(0.f);
      k *= scene_.bsdfs.tex(b.specular_reflectance, v.uv) * fresnel_conductor(ci, b.eta_c, b.k_c);
    } else if (b.type == BSDFType::Dielectric) {
      const DielectricFresnel f = fresnel_dielectric(ci, b.eta);
      if (eta2 && tau[i] != 'R') *eta2 *= double(f.eta_ti) * double(f.eta_ti);
      if (tau[i] == 'R') k *= scene_.bsdfs.tex(b.specular_reflectance, v.uv) * f.F;
      else k *= scene_.bsdfs.tex(b.specular_transmittance, v.uv) * (flux ? (1.f - f.F) : (1.f - f.F) * f.eta_ti * f.eta_ti);
    } else {
      return Color(0.f);
    }
  }
  return k;
}

const ChainDistribution* ChainEstimator::guide_at(const Vec3& xD, const Vec3& xL, Stats* st) const {
  if (!(p_.guide && p_.guide->valid())) return nullptr;
  const bool timed = st && time_guide_call();
  const auto tg = timed ? Clock::now() : Clock::time_point{};
  const ChainDistribution* g = p_.guide->query(xD, xL);
  if (timed) add_guide_time(*st, tg);
  return g;
}

double ChainEstimator::pn_at(const ChainDistribution* guide, int n, int nmax) const {
  return pmf_n_mix(n, nmax, guide, guide ? guide->mass_n(nmax) : 0.0);
}

double ChainEstimator::pt_letters_pdf(const ManifoldChain& c, const std::string& tau) const {
  double p = 1.0;
  const size_t n = c.v.size();
  for (size_t i = 0; i < n; ++i) {
    const ManifoldVertex& v = c.v[i];
    if (v.mf || v.nmap) return -1.0;
    const SurfaceInteraction si = vertex_interaction(c, i);
    const BSDFContext ctx = scene_.bsdfs.resolve(scene_.shapes[size_t(v.shape)].bsdf, si);
    if (!ctx.leaf) return -1.0;
    if (ctx.leaf->type == BSDFType::Dielectric) {
      // BSDFSet::sample_local: reflection with probability F at the shading cosine.
      const float F = fresnel_dielectric(glm::dot(si.wi, ctx.frame.n), ctx.leaf->eta).F;
      p *= tau[i] == 'R' ? double(F) : double(1.f - F);
    } else if (ctx.leaf->type != BSDFType::Conductor) {
      return -1.0;
    }
  }
  return p;
}

double ChainEstimator::pt_density(const ManifoldChain& c, const std::string& tau,
                                  const BSDFContext& ctx, const Vec3& wi, double G) const {
  if (!p_.mis) return 0.0;
  const double letters = pt_letters_pdf(c, tau);
  if (!(letters > 0.0)) return 0.0;
  const Vec3 wD = to_f(glm::normalize(c.v[0].p - c.xD));
  // Solid-angle density at x_D times |d omega_D / dA_L| (G, method-notes Sec. 4).
  const double b = double(scene_.bsdfs.pdf(ctx, wi, wD)) * letters * G;
  return b >= 0.0 ? b : 0.0;  // NaN: not shared
}

Round ChainEstimator::round(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
                            const std::vector<Vec2>& offsets, const ChainDistribution* seed_guide,
                            const std::string& tau_star, const DVec3& w_star, double beta, PCG32& rng,
                            Stats& st, bool tally) const {
  thread_local ManifoldChain other;
  thread_local std::string tau2;
  Round rd;
  mis_round(beta, [&] { return rng.next_double(); }, [&] {
    st.bernoulli_trials++;
    rd.tried = true;
    rd.hit = trial(xD, nD, lp, n, offsets, seed_guide, rng, other, tau2, st, tally ? &rd.tally : nullptr,
                   &tau_star) &&
             tau2 == tau_star && glm::length(glm::normalize(other.v[0].p - xD) - w_star) < p_.uniqueness_threshold;
    return rd.hit;
  });
  return rd;
}

int ChainEstimator::mis_rounds(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
                               const std::vector<Vec2>& offsets, const ChainDistribution* seed_guide,
                               const std::string& tau_star, const DVec3& w_star, double beta,
                               PCG32& rng, Stats& st, bool& capped, std::vector<Round>* rounds) const {
  return bernoulli_count(
      [&] {
        if (st.cancelled()) return true;  // the pass is dropped: any value will do
        const Round rd = round(xD, nD, lp, n, offsets, seed_guide, tau_star, w_star, beta, rng, st, rounds);
        if (rounds) rounds->push_back(rd);
        return !rd.tried || rd.hit;
      },
      p_.max_trials, capped);
}

void ChainEstimator::tally_limits(const TrialTally& first, const std::vector<Round>* rounds, const Color& X,
                                  int K, double q, const std::function<Round(Stats&)>& more, Stats& st,
                                  bool pt) const {
  // Under limit H (slot h) the walks are the full search's until H stops one
  // (WalkResult::limited_tries): the first trial finds the same solution iff
  // H >= its later_rejections, and a round succeeds iff its coin does or its
  // trial finds the solution with later_rejections <= H. So X_H = X K_H / K
  // (X is linear in K) with K_H the first such round, and its walks' steps are
  // those of rounds 1..K_H under H. The expectations are the limited
  // estimator's exactly; the rounds past K only feed these counts.
  auto keeps = [](int later, int h) { return h == kFullSearch || later <= h; };
  std::array<double, kHalvingSlots> steps{};
  std::array<int, kHalvingSlots> KH{};
  for (int h = 0; h < kHalvingSlots; ++h) steps[size_t(h)] = first.steps[size_t(h)];
  const bool estimated = rounds != nullptr && K > 0;
  int open = 0;  // limits still counting rounds
  for (int h = 0; h < kHalvingSlots; ++h)
    if (estimated && keeps(first.later_rejections, h)) { KH[size_t(h)] = -1; ++open; }
  auto take = [&](const Round& rd, int index) {
    for (int h = 0; h < kHalvingSlots; ++h) {
      if (KH[size_t(h)] != -1) continue;
      if (rd.tried) steps[size_t(h)] += rd.tally.steps[size_t(h)];
      if (!rd.tried || (rd.hit && keeps(rd.tally.later_rejections, h))) {
        KH[size_t(h)] = index;
        --open;
      }
    }
  };
  int index = 0;
  if (estimated)
    for (const Round& rd : *rounds) take(rd, ++index);
  // The extra rounds stop at 16 K + 64 (and max_trials): a limit that finds the
  // solution that much less often is counted as censored, and mpg's choice
  // leaves it out (a limit under which P_H ~ 0 would otherwise run up to
  // max_trials walks per estimate in training).
  const int cap = std::min(p_.max_trials, 16 * K + 64);
  if (open > 0 && index < cap) {
    Stats scratch;
    scratch.cancel = st.cancel;
    while (open > 0 && index < cap && !st.cancelled()) take(more(scratch), ++index);
  }
  for (int h = 0; h < kHalvingSlots; ++h) {
    if (KH[size_t(h)] == -1) {
      KH[size_t(h)] = index;
      st.limit_censored[size_t(h)]++;
    }
    (pt ? st.limit_pt_steps : st.limit_steps)[size_t(h)] += steps[size_t(h)];
    if (!estimated || KH[size_t(h)] == 0) continue;
    const double r = double(KH[size_t(h)]) / double(K);
    const double m2 = r * r * mean_square(X) / q;
    if (std::isfinite(m2)) (pt ? st.limit_pt_m2 : st.limit_m2)[size_t(h)] += m2;
  }
}

int ChainEstimator::pt_densities(const SurfaceInteraction& sep, const BSDFContext& sep_ctx,
                                 uint32_t sep_depth, uint32_t max_depth, const SurfaceInteraction* verts,
                                 const std::string& tau, const SurfaceInteraction& light,
                                 ManifoldChain& c, LightPoint& lp, const ChainDistribution*& guide,
                                 double& a, double& b, Stats* st, const LeafQuery* known) const {
  if (!p_.mis || !light.valid) return 0;
  const int emitter = scene_.shapes[size_t(light.shape)].emitter;
  if (emitter < 0) return 0;
  const int k = light_index_[size_t(emitter)];
  if (k < 0) return 1;  // not a chain emitter: the estimator never samples it
  const Emitter& e = scene_.emitters[size_t(emitter)];
  if (e.type != Emitter::Type::Area) return 0;
  const int n = int(tau.size());
  c.xD = to_d(sep.p);
  c.nD = to_d(sep.ng);
  c.xL = to_d(light.p);
  c.nL = to_d(light.ng);
  c.v.resize(size_t(n));
  for (int i = 0; i < n; ++i) {
    if (!walk_.make_vertex(verts[i], tau[size_t(i)] == 'R', c.v[size_t(i)], nullptr)) return 0;
    if (c.v[size_t(i)].mf || c.v[size_t(i)].nmap) return 0;  // not shared: no walk needed
  }
  lp.p = c.xL;
  lp.n = c.nL;
  lp.value = e.value;
  lp.pdf = area_light_pdf(size_t(k));
  lp.point = false;
  lp.emitter = emitter;
  guide = known && known->done ? known->leaf : guide_at(sep.p, light.p, st);
  a = lp.pdf * pn_at(guide, n, max_len(sep_depth, max_depth));
  if (!(a > 0.0)) return 1;  // P(n) = 0: the estimator never draws this length
  // The traced path leaves each vertex from an offset origin, so it misses the
  // exact chain of its endpoints by ~1e-4 in direction, and G near a fold is
  // sensitive to that: a walk (one or two Newton steps) puts it on the chain the
  // estimator would find, so both sides evaluate a and b at the same path. If
  // that walk fails (rare), b is taken at the traced vertices.
  const ManifoldChain traced = c;
  if (!walk_.solve(c).converged) c = traced;
  double G = 0.0;
  if (!walk_.geometry_area(c, G) || !(G >= 0.0)) return 0;
  b = pt_density(c, tau, sep_ctx, sep.wi, G);
  return b > 0.0 ? 2 : 0;
}

float ChainEstimator::pt_weight(const SurfaceInteraction& sep, const BSDFContext& sep_ctx,
                                uint32_t sep_depth, uint32_t max_depth, const SurfaceInteraction* verts,
                                const std::string& tau, const SurfaceInteraction& light, PCG32& rng,
                                Stats& st, const Color& unit, const LeafQuery* known, bool* whole) const {
  thread_local ManifoldChain c;
  thread_local std::vector<Vec2> offsets;
  LightPoint lp;
  const ChainDistribution* guide = nullptr;
  double a = 0.0, b = 0.0;
  const int shared = pt_densities(sep, sep_ctx, sep_depth, max_depth, verts, tau, light, c, lp, guide, a, b, &st, known);
  if (shared != 2) {
    // (whole: a light or length the estimator never produces, the path tracer's alone)
    if (whole) *whole = shared == 1;
    return shared == 1 ? 1.f : 0.f;
  }
  b = rate_b(b, st);  // mis_rate: b / q, q this pixel's rate (as estimate() takes it)
  if (!std::isfinite(b)) return 1.f;  // the estimator's share a P / (a P + b) vanishes
  // b / (a P + b) = b / (a + b) * E[K'] with the estimator's own trials
  // (same n, leaf and seed mixture) aiming at this chain.
  const int n = int(tau.size());
  offsets.assign(size_t(n), Vec2(0.5f));  // smooth chains: unused
  const ChainDistribution* seed_guide = (guide && (p_.guide_tau || p_.guide_dir)) ? guide : nullptr;
  const DVec3 w_star = glm::normalize(c.v[0].p - c.xD);
  bool capped = false;
  const auto tb = Clock::now();
  thread_local std::vector<Round> rounds;
  rounds.clear();
  const double beta = a / (a + b);
  const int K = mis_rounds(c.xD, c.nD, lp, n, offsets, seed_guide, tau, w_star, beta, rng, st, capped,
                           p_.count_limits ? &rounds : nullptr);
  st.bernoulli_ns += ns_since(tb);
  if (capped) st.bernoulli_capped++;
  const float w = float(b / (a + b) * double(K));
  if (p_.count_limits) {
    // The path tracer's share moves with the estimator's P under a limit
    // (b / (a P_H + b)): its value unit x w, counted as the estimates' are.
    const Color Y = unit * w;
    if (const double m2 = mean_square(Y); std::isfinite(m2)) st.pt_shared_m2 += m2;
    tally_limits(TrialTally{}, &rounds, Y, K, 1.0, [&](Stats& scratch) {
      return round(c.xD, c.nD, lp, n, offsets, seed_guide, tau, w_star, beta, rng, scratch, true);
    }, st, true);
  }
  return w;
}

bool ChainEstimator::mis_pair(const Vec3& o, const Vec3& d, const Vec3& omega_D, const Vec3& seed_dir,
                              const std::string& tau, double ab[4]) const {
  const SurfaceInteraction sep = scene_.intersect(o, glm::normalize(d), 0.f, kInf);
  if (!sep.valid || tau.empty()) return false;
  const BSDFContext ctx = scene_.bsdfs.resolve(scene_.shapes[size_t(sep.shape)].bsdf, sep);
  if (!ctx.leaf) return false;
  // Path tracer's side: ideal scattering along the letters, then an emitter.
  std::vector<SurfaceInteraction> verts;
  Vec3 org = sep.p, ng = sep.ng, dir = glm::normalize(omega_D);
  for (char letter : tau) {
    const SurfaceInteraction si = scene_.intersect(offset_ray_origin(org, ng, dir), dir, 0.f, kInf);
    ManifoldVertex v;
    if (!si.valid || !is_chain_shape(si.shape) || !walk_.make_vertex(si, letter == 'R', v, nullptr)) return false;
    DVec3 wo;
    if (!ManifoldWalk::scatter(-to_d(dir), v.n, v.eta, letter == 'R', wo)) return false;
    verts.push_back(si);
    org = si.p;
    ng = si.ng;
    dir = to_f(wo);
  }
  const SurfaceInteraction light = scene_.intersect(offset_ray_origin(org, ng, dir), dir, 0.f, kInf);
  if (!light.valid || scene_.shapes[size_t(light.shape)].emitter < 0) return false;
  ManifoldChain cp;
  LightPoint lp;
  const ChainDistribution* guide = nullptr;
  ab[2] = ab[3] = 0.0;
  if (pt_densities(sep, ctx, 0, uint32_t(-1), verts.data(), tau, light, cp, lp, guide, ab[2], ab[3]) != 2) {
    if (p_.mis) return false;
    ab[2] = ab[3] = 0.0;
  }
  // Estimator's side: a walk from another seed to the same x_L.
  ManifoldChain c;
  c.xL = to_d(light.p);
  c.nL = to_d(light.ng);
  WalkFailure why = WalkFailure::None;
  if (!walk_.trace_seed(to_d(sep.p), to_d(sep.ng), to_d(seed_dir), tau, c, why)) return false;
  if (!walk_.solve(c).converged) return false;
  // the same path (a configuration can have several TT solutions)
  if (glm::length(glm::normalize(c.v[0].p - to_d(sep.p)) - to_d(glm::normalize(omega_D))) > 1e-2) return false;
  double G = 0.0;
  if (!walk_.geometry_area(c, G)) return false;
  const int emitter = scene_.shapes[size_t(light.shape)].emitter;
  if (light_index_[size_t(emitter)] < 0) return false;
  ab[0] = area_light_pdf(size_t(light_index_[size_t(emitter)])) * pn_at(guide_at(sep.p, light.p, nullptr), int(tau.size()), max_len(0, uint32_t(-1)));
  ab[1] = pt_density(c, tau, ctx, sep.wi, G);
  return true;
}

double ChainEstimator::guided_trace_pdf(const Vec3& xD, size_t k, int n, uint16_t bits, const Vec3& wD, int nmax,
                                        Stats* st) const {
  if (n < 1 || n > nmax || scene_.emitters[size_t(chain_lights_[k])].type != Emitter::Type::Area) return 0.0;
  const ChainDistribution* leaf = guide_at(xD, light_centre_[k], st);
  return leaf ? leaf_trace_pdf(*leaf, k, n, bits, xD, wD, st ? &st->trace_pt_lobes : nullptr) : 0.0;
}

double ChainEstimator::leaf_trace_pdf(const ChainDistribution& leaf, size_t k, int n, uint16_t bits,
                                      const Vec3& xD, const Vec3& wD, uint64_t* lobes) const {
  if (lobes) *lobes += leaf.lobe_count(n, bits);
  // (with trace_defensive the direction's density is the mixture guided_trace_one draws from)
  const double pdir = p_.trace_defensive > 0.f
                          ? leaf.pdf_dir_defensive(n, bits, xD, wD, double(p_.trace_defensive), p_.trace_defensive_kappa)
                          : double(leaf.pdf_dir(n, bits, xD, wD));
  return double(light_dist_.pmf(k)) * double(leaf.pmf_n(n)) * double(leaf.pmf_tau(n, bits)) * pdir;
}

Color ChainEstimator::guided_trace(const SurfaceInteraction& si, const BSDFContext& ctx, uint32_t depth,
                                   uint32_t max_depth, int k, PCG32& rng, Stats& st) const {
  // k traces, each weighted by the balance heuristic of k samples of density g
  // against the path tracer's one of density b (Veach's multi-sample form):
  // f / (b + k g) each
  Color sum(0.f);
  for (int j = 0; j < k; ++j) sum += guided_trace_one(si, ctx, depth, max_depth, rng, st).weighted(k);
  return sum;
}

ChainEstimator::TraceSample ChainEstimator::guided_trace_one(const SurfaceInteraction& si, const BSDFContext& ctx,
                                                             uint32_t depth, uint32_t max_depth, PCG32& rng,
                                                             Stats& st) const {
  // Draws: the light k by power, (n, tau, omega_D) from the leaf of (x_D, its
  // centre); then the ray follows tau's letters through delta vertices of chain
  // shapes (each lobe forced, weighted by its probability as in delta_tree) and
  // must end on light k. Its density g per solid angle at x_D (and letter
  // choice) is guided_trace_pdf; the path tracer's b = pdf_bsdf(omega_D) times
  // its Fresnel choices (pt_letters_pdf's rule). Returned unweighted, (f =
  // throughput * Le, b, g): with k traces each contributes f / (b + k g)
  // (TraceSample::weighted). The random numbers are drawn up front, a fixed
  // count per call. (k below is the light's index, not a count of traces.)
  const int nmax = max_len(depth, max_depth);
  float u_light = rng.next_float();  // (sample() reuses it)
  const float u_n = rng.next_float(), u_t = rng.next_float();
  const double u_lobe = rng.next_double();
  const Vec2 u_dir(rng.next_float(), rng.next_float());
  // (the defensive share's draw only when it is on: the traces' random
  // streams, and so the images, are unchanged without it)
  const bool defensive = p_.trace_defensive > 0.f && rng.next_float() < p_.trace_defensive;
  if (nmax < 1) return TraceSample{};
  const size_t k = light_dist_.sample(u_light);
  const Emitter& em = scene_.emitters[size_t(chain_lights_[k])];
  if (em.type != Emitter::Type::Area) return TraceSample{};
  const ChainDistribution* leaf = guide_at(si.p, light_centre_[k], &st);
  if (!leaf) return TraceSample{};
  st.guided_traces++;
  const int n = leaf->sample_n(u_n);
  if (n < 1 || n > nmax) return TraceSample{};
  const int t = leaf->sample_type(n, u_t);
  Vec3 wD;
  if (t < 0 || !leaf->sample_dir_of(t, u_lobe, u_dir, si.p, wD,
                                    defensive ? p_.trace_defensive_kappa : std::numeric_limits<float>::infinity()))
    return TraceSample{};
  if (defensive) st.guided_traces_defensive++;
  const uint16_t bits = leaf->type_tau(t);
  const Color f = scene_.bsdfs.eval(ctx, si.wi, wD);
  if (is_black(f)) return TraceSample{};
  Color thr = f;
  double letters = 1.0;
  Vec3 o = si.p, ng = si.ng, d = wD;
  SurfaceInteraction h;
  for (int i = 0; i <= n; ++i) {
    st.rays++;
    h = scene_.intersect(offset_ray_origin(o, ng, d), d, 0.f, kInf);
    if (!h.valid) return TraceSample{};
    if (i == n) break;
    if (!is_chain_shape(h.shape)) return TraceSample{};
    const BSDFContext c = scene_.bsdfs.resolve(scene_.shapes[size_t(h.shape)].bsdf, h);
    if (!c.leaf || !c.leaf->is_delta()) return TraceSample{};
    const bool want_r = (bits >> i) & 1u;
    Vec3 wo;
    const BSDFSample bs = scene_.bsdfs.sample(c, h.wi, want_r ? 0.f : 1.f, Vec2(0.5f), wo);
    if (!(bs.pdf > 0.f) || !bs.delta || bs.null || bs.transmission == want_r || is_black(bs.weight))
      return TraceSample{};
    thr *= bs.weight * bs.pdf;
    letters *= double(bs.pdf);
    o = h.p;
    ng = h.ng;
    d = wo;
  }
  if (scene_.shapes[size_t(h.shape)].emitter != chain_lights_[k]) return TraceSample{};
  const Color Le = scene_.emitted(h);
  if (is_black(Le)) return TraceSample{};
  // guided_trace_pdf with the leaf already at hand (the same leaf: the same x_D and centre)
  const double g = leaf_trace_pdf(*leaf, k, n, bits, si.p, wD, &st.trace_lobes);
  const double b = double(scene_.bsdfs.pdf(ctx, si.wi, wD)) * letters;
  if (!(g > 0.0) || !std::isfinite(b + g)) return TraceSample{};
  TraceSample ts;
  ts.f = thr * Le;
  ts.b = b;
  ts.g = g;
  ts.tail_ok = glm::dot(si.wi, si.ng) * glm::dot(wD, si.ng) > 0.f;
  st.guided_trace_hits++;
  return ts;
}

bool ChainEstimator::pt_letter(const SurfaceInteraction& v, char letter, BSDFSample& bs) const {
  const BSDFContext c = scene_.bsdfs.resolve(scene_.shapes[size_t(v.shape)].bsdf, v);
  if (!c.leaf || !c.leaf->is_delta()) return false;
  Vec3 wo;
  bs = scene_.bsdfs.sample(c, v.wi, letter == 'R' ? 0.f : 1.f, Vec2(0.5f), wo);
  return bs.pdf > 0.f && bs.delta && !bs.null && bs.transmission == (letter == 'T');
}

bool ChainEstimator::guided_trace_densities(const SurfaceInteraction& sep, const BSDFContext& sep_ctx,
                                            uint32_t sep_depth, uint32_t max_depth, const Vec3& wD,
                                            const SurfaceInteraction* verts, const std::string& tau,
                                            const SurfaceInteraction& light, Stats& st, double& b,
                                            double& g) const {
  const int emitter = scene_.shapes[size_t(light.shape)].emitter;
  if (emitter < 0 || light_index_[size_t(emitter)] < 0) return false;
  const int n = int(tau.size());
  if (n < 1 || n > ChainDistribution::kMaxN) return false;
  // The letters' probabilities as the path tracer drew them (Fresnel at
  // dielectrics, 1 at conductors), the same numbers guided_trace multiplies
  // into its b; a vertex the guided trace cannot pass (not delta) gives g = 0.
  double letters = 1.0;
  for (int i = 0; i < n; ++i) {
    BSDFSample bs;
    if (!pt_letter(verts[i], tau[size_t(i)], bs)) return false;
    letters *= double(bs.pdf);
  }
  // (wD is the sampled direction, not rebuilt from the hit points: the ray left
  // from an offset origin, and a lobe of kappa up to 1e8 would see the difference)
  g = guided_trace_pdf(sep.p, size_t(light_index_[size_t(emitter)]), n, tau_bits(tau.data(), n), wD,
                       max_len(sep_depth, max_depth), &st);
  if (!(g > 0.0)) return false;
  b = double(scene_.bsdfs.pdf(sep_ctx, sep.wi, wD)) * letters;
  return std::isfinite(b);   // the trace rejects such a path too (its b + k g is not finite)
}

float ChainEstimator::guided_trace_pt_weight(bool shared, double b, double g, int k) {
  if (!shared || k < 1) return 1.f;
  const double w = b / (b + double(k) * g);
  return std::isfinite(w) ? float(w) : 1.f;
}

Color ChainEstimator::estimate(const SurfaceInteraction& si, const BSDFContext& ctx, uint32_t depth,
                               uint32_t max_depth, PCG32& rng, Stats& st, const Color& beta,
                               PathDensities* dens) const {
  if (!active_) return Color(0.f);
  const int nmax = max_len(depth, max_depth);
  if (nmax < 1) return Color(0.f);
  const auto t0 = Clock::now();
  const uint64_t steps0 = st.walk_steps;
  st.chain_estimates++;
  Color result(0.f);
  LightPoint lp;
  const DVec3 xD = to_d(si.p), nD = to_d(si.ng);
  ManifoldChain chain;
  std::string tau;
  TrialTally first;          // count_limits: the first trial's work under each limit
  bool tried_first = false, tallied = false;
  thread_local std::vector<Round> rounds;
  do {
    if (!sample_light(rng, lp)) break;
    // A point or spot light's chains at the camera's first hit are the light
    // tracer's (integrators/light_trace.h), and with light_trace_area an area
    // light's too: the same selection, value 0 here.
    if (st.chain_skip_delta_lights && (lp.point || st.chain_skip_area_lights)) {
      st.chain_lt_skipped++;
      break;
    }
    // The leaf of (x_D, x_L): learned distribution, and selective activation.
    const ChainDistribution* guide = guide_at(to_f(xD), to_f(lp.p), &st);
    if (!guide && p_.guide && p_.guide->valid() && p_.selective) {
      st.chain_inactive++;
      break;
    }
    const double mass = guide ? guide->mass_n(nmax) : 0.0;
    int n;
    if (guide && p_.guide_n && mass > 0.0 && rng.next_float() < p_.guide_fraction) {
      // n from P_e truncated at nmax (inverse CDF over the allowed lengths)
      const double u = double(rng.next_float()) * mass;
      double c = 0.0;
      n = nmax;
      for (int k = 1; k <= nmax; ++k) {
        c += guide->pmf_n(k);
        if (u < c) { n = k; break; }
      }
    } else {
      n = sample_n(rng.next_float(), nmax);
    }
    const double pn = pmf_n_mix(n, nmax, guide, mass);  // as pn_at, with the mass just summed
    // Offset normals of glossy vertices: drawn once, shared by all trials (the
    // admissible set is finite given them; method-notes Sec. 7).
    thread_local std::vector<Vec2> offsets;  // reused: no allocation per estimate
    offsets.resize(static_cast<size_t>(n));
    for (auto& o : offsets) o = Vec2(rng.next_float(), rng.next_float());
    const ChainDistribution* seed_guide = (guide && (p_.guide_tau || p_.guide_dir)) ? guide : nullptr;
    tried_first = true;
    if (!trial(xD, nD, lp, n, offsets, seed_guide, rng, chain, tau, st, p_.count_limits ? &first : nullptr))
      break;
    st.chain_converged++;
    // A type the leaf never saw, to an area light: the path tracer's whole
    // (known_types; active_for on its side gives the same answer).
    if (p_.known_types && guide && !lp.point && !guide->has_type(n, tau_bits(tau.data(), n))) {
      st.chain_unknown_type++;
      break;
    }
    const ManifoldVertex& last = chain.v.back();
    // One-sided area light; visibility of the last segment (the others are first hits).
    if (!lp.point && glm::dot(last.p - lp.p, lp.n) <= 0.0) break;
    const Vec3 wD = to_f(glm::normalize(chain.v[0].p - xD));
    const Color f = scene_.bsdfs.eval(ctx, si.wi, wD);
    if (is_black(f)) break;
    const Color kap = kappa(chain, tau, lp.point);
    if (is_black(kap)) break;
    st.shadow_rays++;
    if (scene_.occluded_to(to_f(last.p), to_f(last.ng), to_f(lp.p))) break;
    double G = 0.0;
    Color Le = lp.value;
    if (lp.point) {
      if (!walk_.geometry_point(chain, G)) break;
      const Emitter& e = scene_.emitters[size_t(lp.emitter)];
      if (e.type == Emitter::Type::Spot) Le *= e.spot_falloff(e.frame.to_local(glm::normalize(to_f(last.p - lp.p))));
    } else {
      if (!walk_.geometry_area(chain, G)) break;
    }
    // Balance heuristic with the path tracer's own continuation (design-notes,
    // "Chain paths shared with the path tracer"): with a = p(x_L) P(n) and b its
    // density, the estimate F / (a P + b) = F K' / (a + b), E[K'] = (a + b) / (a P + b)
    // by the MIS-aware Bernoulli rounds. b = 0 (point/spot lights, glossy or
    // normal-mapped chains, mis off): SMS's F K / a, <1/P> = K (supplemental Sec. 3.2).
    const double a = lp.pdf * pn;
    const double b = lp.point ? 0.0 : rate_b(pt_density(chain, tau, ctx, si.wi, G), st);
    if (!std::isfinite(b)) break;  // a P / (a P + b) = 0
    const DVec3 w_star = glm::normalize(chain.v[0].p - xD);
    const std::string tau_star = tau;
    bool capped = false;
    const auto tb = Clock::now();
    rounds.clear();
    const int K = mis_rounds(xD, nD, lp, n, offsets, seed_guide, tau_star, w_star, a / (a + b), rng, st, capped,
                             p_.count_limits ? &rounds : nullptr);
    st.bernoulli_ns += ns_since(tb);
    if (capped) st.bernoulli_capped++;
    if (p_.record && !capped) {
      // Sub-path sample for the next training iteration: w = T <1/P> (MPG Eq. 9),
      // times the estimator's share a P / (a P + b) of the path when it is shared
      // (K a / (a + b) estimates that share over P; = K when b = 0). With
      // mis_rate b is b / q_t here: the share at the training passes' rate.
      SubpathSample ss;
      for (int c = 0; c < 3; ++c) { ss.xD[c] = float(xD[c]); ss.xL[c] = float(lp.p[c]); }
      const Vec2 e = oct_encode(to_f(w_star));
      ss.dir[0] = e.x;
      ss.dir[1] = e.y;
      ss.weight = luminance(kap * Le) * float(G * double(K) * a / (a + b));
      // Product sampling with the separator's BSDF (MPG Eq. 14): the weight also
      // carries rho(omega_i, omega_D*) (here with |cos theta_D|, the integrand's factor).
      if (p_.product) ss.weight *= luminance(f);
      ss.n = uint8_t(n);
      ss.tau = tau_bits(tau_star.data(), n);
      ss.flags = 0;
      if (std::isfinite(ss.weight) && ss.weight > 0.f) st.subpaths.push_back(ss);
    }
    double scale = G * double(K) / (a + b);
    if (lp.point) {
      // Irradiance I kappa G, G = |d omega_L / dA_D| with the geometric
      // cosine at x_D; f carries the shading frame's |cos theta_D|, so the
      // radiance is f_s |cos_s| E / |cos_g| (as next-event estimation's f I / d^2
      // and the light tracer's splat; the same for a flat receiver).
      const float cosD = std::abs(glm::dot(wD, si.ng));
      if (!(cosD > 0.f)) break;
      scale /= double(cosD);
    }
    result = f * kap * Le * float(scale);
    st.chain_contributions++;
    // (the paths the tails cover: delta chain vertices only, at most kMaxN, a
    // reflection at x_D -- the path tracer's side leaves out the same)
    bool tails = dens && !lp.point && n <= ChainDistribution::kMaxN &&
                 glm::dot(si.wi, si.ng) * glm::dot(wD, si.ng) > 0.f;
    for (const ManifoldVertex& v : chain.v) tails = tails && !v.mf;
    if (tails) {
      // (pt_density's factors without G: both densities per solid angle at x_D;
      // the letters' probabilities as the path tracer draws them, normal maps
      // included, as guided_trace_densities takes them)
      const float pdf = scene_.bsdfs.pdf(ctx, si.wi, wD);
      double letters = 1.0;
      for (int i = 0; i < n; ++i) {
        // the path tracer's draw of the letter: its probability, weight and eta
        BSDFSample bs;
        if (!pt_letter(vertex_interaction(chain, size_t(i)), tau_star[size_t(i)], bs)) {
          letters = 0.0;
          break;
        }
        letters *= double(bs.pdf);
        dens->w[size_t(i)] = bs.weight;
        dens->eta[size_t(i)] = bs.eta;
      }
      dens->unit = f * kap * Le;
      dens->b = double(pdf) * letters;
      dens->g = 0.0;
      dens->n = n;
      dens->sep_weight = pdf > 0.f ? f / pdf : Color(0.f);
      const int li = light_index_[size_t(lp.emitter)];
      if (dens->want_g && li >= 0) {
        const size_t k = size_t(li);
        if (const ChainDistribution* leaf = guide_at(si.p, light_centre_[k], &st))
          dens->g = leaf_trace_pdf(*leaf, k, n, tau_bits(tau_star.data(), n), si.p, wD, nullptr);
      }
      dens->ok = dens->b > 0.0 && std::isfinite(dens->b) && std::isfinite(dens->g);
    }
    // The largest estimate as it enters the sample: after the roulette's 1/q
    // (path.cpp takes q the same way), where low rates make the fireflies.
    const double q = double(rate_at(st));
    if (p_.count_limits) {
      // The second moment X^2 / q (mean over RGB) this estimate adds to its
      // sample, and what it would have been, and cost, under each limit.
      const Color X = beta * result;   // as it enters the sample (before the roulette's 1/q)
      const double m2 = mean_square(X) / std::max(q, 1e-6);
      if (std::isfinite(m2)) st.chain_m2 += m2;
      const double coin = a / (a + b);
      tally_limits(first, &rounds, X, K, std::max(q, 1e-6), [&](Stats& scratch) {
        return round(xD, nD, lp, n, offsets, seed_guide, tau_star, w_star, coin, rng, scratch, true);
      }, st);
      tallied = true;
    }
    if (const double v = double(luminance(result)) / std::max(q, 1e-6); v > st.max_chain_value) {
      st.max_chain_value = v; st.max_chain_K = K; st.max_chain_G = G; st.max_chain_pn = pn;
      st.max_chain_n = n; st.max_chain_guided = guide ? 1.0 : 0.0; st.max_chain_rate = q;
    }
  } while (false);
  // An estimate that ended after its first trial: the same nothing under every limit, at its cost.
  if (p_.count_limits && tried_first && !tallied) tally_limits(first, nullptr, Color(0.f), 0, 1.0, {}, st);
  st.chain_ns += ns_since(t0);
  // + 1: an estimate's own work (light sample, leaf query, G, the light's shadow ray)
  st.chain_steps += st.walk_steps - steps0 + 1;
  return result;
}

bool ChainEstimator::connect_point(const DVec3& xD, const DVec3& nD, const DVec3& xP, int mmax, PCG32& rng,
                                   Stats& st, ManifoldChain& chain, Color& weight) const {
  if (!active_ || p_.mode != ChainParams::Mode::SmsStar || mmax < 1) return false;
  LightPoint lp;
  lp.p = xP;
  lp.n = DVec3(0.0, 1.0, 0.0);   // (unused for a point)
  lp.value = Color(1.f);
  lp.pdf = 1.0;
  lp.point = true;
  const int m = sample_n(rng.next_float(), mmax);
  const double pm = pmf_n(m, mmax);
  thread_local std::vector<Vec2> offsets;
  offsets.resize(size_t(m));
  for (auto& o : offsets) o = Vec2(rng.next_float(), rng.next_float());
  std::string tau;
  if (!trial(xD, nD, lp, m, offsets, nullptr, rng, chain, tau, st)) return false;
  double G = 0.0;
  if (!walk_.geometry_point(chain, G) || !(G > 0.0)) return false;
  // The lobes' plain weights (reciprocal), then the radiance's scaling toward
  // xP, (eta_P / eta_D)^2: the inverse of kappa's product from x_D toward x_L.
  double eta2 = 1.0;
  Color kap = kappa(chain, tau, true, &eta2);
  if (is_black(kap) || !(eta2 > 0.0)) return false;
  const DVec3 w_star = glm::normalize(chain.v[0].p - xD);
  bool capped = false;
  const int K = mis_rounds(xD, nD, lp, m, offsets, nullptr, tau, w_star, 1.0, rng, st, capped);
  if (capped) st.bernoulli_capped++;
  weight = kap * float(G * double(K) / (pm * eta2));
  return std::isfinite(weight.x) && std::isfinite(weight.y) && std::isfinite(weight.z);
}

// ---- Glints (chain_estimator.h, "The glints"; docs/design-notes.md, "Glints") ----

namespace {
// Seeds whose ray after the chain passes farther than this many times the
// larger of the light's radius and a pixel's footprint at the light skip the
// walk (a cost control, part of the seed process the trials repeat). 16
// against 4 on emitter_size_001 / 003 (128^2, 10 s, 3 seeds): 1.4x / 1.6x the
// glints found, mean K 30 against 55, 8-11 % fewer spp, own MSE level / 1.35x
// lower (docs/results.md, twenty-fourth session); 64 cost half the spp.
constexpr double kGlintCapture = 16.0;
bool glint_captured(const DVec3& o, const DVec3& d, const DVec3& c, double r) {
  const DVec3 oc = c - o;
  // (a vertex inside the sphere: every ray from it to the light passes)
  if (glm::dot(oc, oc) < r * r) return true;
  const double t = glm::dot(oc, d);
  if (!(t > 0.0)) return false;
  return glm::dot(oc, oc) - t * t < r * r;
}
}  // namespace

ChainEstimator::GlintLights ChainEstimator::glint_lights(float max_pixels, int max_depth) const {
  GlintLights gl;
  if (!active_ || !(max_pixels > 0.f)) return gl;
  const Camera& cam = scene_.camera;
  if (cam.filter.type != FilterSampler::Type::Box || std::abs(cam.filter.radius - 0.5f) > 1e-6f) return gl;
  // m chain vertices and the light: m + 1 segments
  const int mmax = max_depth < 0 ? p_.max_chain : std::min(p_.max_chain, max_depth - 1);
  if (mmax < 1) return gl;
  Vec3 lo(kInf), hi(-kInf);
  for (size_t s = 0; s < scene_.shapes.size(); ++s)
    if (specular_shape_[s]) scene_.shapes[s].grow_bounds(lo, hi);
  if (!(lo.x <= hi.x)) return gl;
  const DVec3 chain_c = 0.5 * (to_d(lo) + to_d(hi));
  const DVec3 cam_o = to_d(Vec3(cam.to_world * Vec4(0.f, 0.f, 0.f, 1.f)));
  gl.cam_fwd = glm::normalize(to_d(Vec3(cam.to_world * Vec4(0.f, 0.f, 1.f, 0.f))));
  gl.to_local = glm::inverse(cam.to_world);
  const double px = 2.0 * double(cam.tan_half_x) / cam.width, py = 2.0 * double(cam.tan_half_y) / cam.height;
  gl.a_pix = px * py;
  const double pix = std::min(px, py);   // a pixel's angle at the image centre
  if (!(gl.a_pix > 0.0)) return gl;
  gl.owned.assign(scene_.emitters.size(), 0);
  std::vector<float> w;
  for (int e : chain_lights_) {
    const Emitter& em = scene_.emitters[size_t(e)];
    if (em.type != Emitter::Type::Area || em.shape < 0 || !(em.power > 0.f) || !std::isfinite(em.power)) continue;
    const Shape& sh = scene_.shapes[size_t(em.shape)];
    if (!(sh.area > 0.f)) continue;
    DVec3 c(0.0);
    double r = 0.0;
    if (sh.kind == Shape::Kind::Sphere) {
      c = to_d(sh.center);
      r = double(sh.radius);
    } else {
      Vec3 a(kInf), b(-kInf);
      sh.grow_bounds(a, b);
      if (!(a.x <= b.x)) continue;
      c = 0.5 * (to_d(a) + to_d(b));
      for (const Vec3& q : sh.positions) r = std::max(r, glm::length(to_d(q) - c));
    }
    const double len = glm::length(chain_c - cam_o) + glm::length(c - chain_c);
    if (!(len > 0.0) || !(2.0 * r / len < double(max_pixels) * pix)) continue;
    gl.owned[size_t(e)] = 1;
    gl.emitters.push_back(e);
    gl.centre.push_back(c);
    gl.capture.push_back(kGlintCapture * std::max(r, len * pix));
    w.push_back(em.power);
  }
  if (w.empty()) return gl;
  gl.dist.build(w);
  gl.mmax = mmax;
  return gl;
}

int ChainEstimator::glint_seed(const DVec3& o, const SurfaceInteraction& first, const Vec3& d,
                               int m, PCG32& rng, ManifoldChain& chain, std::string& tau, std::vector<DVec3>& dirs,
                               const std::string* want_tau, Stats& st) const {
  chain.xD = o;
  chain.nD = DVec3(0.0);   // the pinhole: no offset, no chart
  chain.v.clear();
  tau.clear();
  dirs.clear();
  SurfaceInteraction si = first;
  DVec3 dd = glm::normalize(to_d(d));
  for (int i = 0; i < m; ++i) {
    if (i > 0) {
      const ManifoldVertex& pv = chain.v.back();
      st.rays++;
      si = scene_.intersect(offset_ray_origin(to_f(pv.p), to_f(pv.ng), to_f(dd)), to_f(dd), 0.f, kInf);
    }
    st.walk_steps++;
    // the path tracer's chain vertices: chain shapes with smooth BSDFs (a
    // glossy one needs offsets: not a glint; the path tracer keeps those paths)
    if (!si.valid || !is_chain_shape(si.shape)) return i;
    ManifoldVertex v;
    if (!walk_.make_vertex(si, true, v)) return i;
    const DVec3 wi = -dd;
    bool reflect = true;
    if (v.dielectric) reflect = rng.next_float() < fresnel_dielectric(float(glm::dot(wi, v.n)), float(v.eta)).F;
    if (want_tau && size_t(i) < want_tau->size() && (reflect ? 'R' : 'T') != (*want_tau)[size_t(i)]) {
      st.trials_tau_cut++;
      return i;
    }
    v.reflect = reflect;
    if (!ManifoldWalk::scatter(wi, v.n, v.eta, reflect, dd)) return i;
    tau.push_back(reflect ? 'R' : 'T');
    chain.v.push_back(v);
    dirs.push_back(dd);
  }
  return m;
}

Color ChainEstimator::glint(const GlintLights& gl, const Vec3& o, const Vec3& d, const SurfaceInteraction& si,
                            int fx, int fy, PCG32& rng, Stats& st) const {
  Color sum(0.f);
  if (!gl.usable() || !si.valid || !is_chain_shape(si.shape)) return sum;
  st.glint_seeds++;
  // x_L: a light by power, a point uniform by area
  float ul = rng.next_float();
  const size_t k = gl.dist.sample(ul);
  const Emitter& em = scene_.emitters[size_t(gl.emitters[k])];
  const Shape& ls = scene_.shapes[size_t(em.shape)];
  Vec3 lp, ln;
  ls.sample_position(Vec2(rng.next_float(), rng.next_float()), lp, ln);
  const double pdf = double(gl.dist.pmf(k)) / double(ls.area);
  const DVec3 xL = to_d(lp), nL = to_d(ln);
  const Camera& cam = scene_.camera;
  ManifoldChain seed;
  std::string letters;
  thread_local std::vector<DVec3> dirs, dirs2;
  const int got = glint_seed(to_d(o), si, d, gl.mmax, rng, seed, letters, dirs, nullptr, st);
  for (int m = 1; m <= got; ++m) {
    if (!glint_captured(seed.v[size_t(m - 1)].p, dirs[size_t(m - 1)], gl.centre[k], gl.capture[k])) continue;
    ManifoldChain chain;
    chain.xD = seed.xD;
    chain.nD = seed.nD;
    chain.v.assign(seed.v.begin(), seed.v.begin() + m);
    chain.xL = xL;
    chain.nL = nL;
    st.glint_walks++;
    const WalkResult r = walk_.solve(chain);
    count_walk(r, m, st, nullptr);
    if (!r.converged) {
      st.walk_failures[size_t(r.failure)]++;
      continue;
    }
    // where the camera sees the solution: this sample's pixel, or another's
    const DVec3 w_star = glm::normalize(chain.v[0].p - chain.xD);
    Vec2 film;
    if (!cam.film_position(gl.to_local * Vec4(to_f(chain.v[0].p), 1.f), film)) continue;
    if (!(std::floor(film.x) == float(fx) && std::floor(film.y) == float(fy))) continue;
    const double cos_c = glm::dot(w_star, gl.cam_fwd);
    if (!(cos_c > 0.0)) continue;
    const ManifoldVertex& last = chain.v.back();
    if (glm::dot(last.p - xL, nL) <= 0.0) continue;   // one-sided light
    const std::string tau = letters.substr(0, size_t(m));
    const Color kap = kappa(chain, tau);
    if (is_black(kap)) continue;
    st.shadow_rays++;
    if (scene_.occluded_to(to_f(last.p), to_f(last.ng), lp)) continue;
    double G = 0.0;
    if (!walk_.geometry_area(chain, G) || !(G > 0.0)) continue;
    // K: seeds from a uniform point of this pixel until one finds (tau, w*)
    bool capped = false;
    const int K = bernoulli_count(
        [&]() {
          st.glint_trials++;
          const float u0 = rng.next_float(), u1 = rng.next_float();
          Vec3 o2, d2;
          float tmin, tmax;
          cam.generate_ray(Vec2(float(fx) + u0, float(fy) + u1), o2, d2, tmin, tmax);
          st.rays++;
          const SurfaceInteraction s2 = scene_.intersect(o2, d2, tmin, tmax);
          ManifoldChain c2;
          std::string t2;
          if (glint_seed(to_d(o2), s2, d2, m, rng, c2, t2, dirs2, &tau, st) < m) return false;
          if (!glint_captured(c2.v[size_t(m - 1)].p, dirs2[size_t(m - 1)], gl.centre[k], gl.capture[k])) return false;
          c2.xL = xL;
          c2.nL = nL;
          const WalkResult r2 = walk_.solve(c2);
          count_walk(r2, m, st, nullptr);
          if (!r2.converged) return false;
          return glm::length(glm::normalize(c2.v[0].p - c2.xD) - w_star) < p_.uniqueness_threshold;
        },
        p_.max_trials, capped);
    if (capped) st.glint_capped++;
    const double scale = G * double(K) / (pdf * gl.a_pix * cos_c * cos_c * cos_c);
    const Color v = kap * em.value * float(scale);
    if (!(std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z))) {
      st.glint_rejected++;
      continue;
    }
    st.glint_found++;
    sum += v;
  }
  // (its work counts in walk_steps and rays, the camera sample's cost; not in
  // chain_steps / chain_ns, the separators' chain estimates' cost per pixel
  // that mpg's learned rates weigh)
  return sum;
}

uint64_t ChainEstimator::trace_photons(uint64_t count, uint64_t seed,
                                       std::vector<SubpathSample>& out, int threads,
                                       uint64_t begin, uint64_t end) const {
  if (!active_) return 0;
  if (end == 0 || end > count) end = count;
  if (begin >= end) return 0;
  const uint64_t span = end - begin;
  // In parallel over blocks of photon indices, each block's samples in its own
  // vector, appended in index order: every photon has its own stream, so the
  // buffer is the same as one thread's, whatever the thread count.
  const uint64_t cores = std::max<uint64_t>(1, std::thread::hardware_concurrency());
  const uint64_t want = threads > 0 ? std::min<uint64_t>(uint64_t(threads), cores) : cores;
  const uint64_t nthreads = std::max<uint64_t>(1, std::min<uint64_t>(want, span / 4096));
  std::vector<std::vector<SubpathSample>> parts(size_t(nthreads - 1));
  auto block = [&](uint64_t t) {
    trace_photon_range(begin + span * t / nthreads, begin + span * (t + 1) / nthreads, count, seed,
                       t == 0 ? out : parts[size_t(t - 1)]);
  };
  std::vector<std::thread> pool;
  for (uint64_t t = 1; t < nthreads; ++t) pool.emplace_back(block, t);
  block(0);
  for (auto& th : pool) th.join();
  for (const auto& v : parts) out.insert(out.end(), v.begin(), v.end());
  return span;
}

// Photons [begin, end) of trace_photons(count, seed, ...), appended to `out`.
void ChainEstimator::trace_photon_range(uint64_t begin, uint64_t end, uint64_t count, uint64_t seed,
                                        std::vector<SubpathSample>& out) const {
  const int nmax = std::min(p_.max_chain, 16);
  for (uint64_t i = begin; i < end; ++i) {
    PCG32 rng = make_stream(seed, 0x70686f746f6eULL /* "photon" */, i, 0);
    // Emission: light and position as the estimator draws x_L (sample_light:
    // light by power, position by area), then a direction cosine-weighted
    // (area), uniform (point) or uniform in the cone (spot). flux = Le cos / pdf.
    LightPoint lp;
    if (!sample_light(rng, lp)) continue;
    const Emitter& e = scene_.emitters[size_t(lp.emitter)];
    const Vec3 xL = to_f(lp.p);
    Vec3 d;
    Color flux;
    if (!lp.point) {
      const Vec3 dl = warp::square_to_cosine_hemisphere(Vec2(rng.next_float(), rng.next_float()));
      d = Frame(to_f(lp.n)).to_world(dl);
      flux = lp.value * float(kPi / lp.pdf);
    } else if (e.type == Emitter::Type::Point) {
      d = warp::square_to_uniform_sphere(Vec2(rng.next_float(), rng.next_float()));
      flux = lp.value * float(4.0 * kPi / lp.pdf);
    } else {  // spot: uniform in the cone of cos_cutoff, weighted by the falloff
      const Vec3 dl = warp::square_to_uniform_cone(Vec2(rng.next_float(), rng.next_float()), e.cos_cutoff);
      d = e.frame.to_world(dl);
      flux = lp.value * float(e.spot_falloff(dl) / (warp::uniform_cone_pdf(dl, e.cos_cutoff) * lp.pdf));
    }
    if (is_black(flux)) continue;
    // Walk through chain vertices, sampling each one's BSDF (R/T by Fresnel at
    // smooth dielectrics), until the first separator.
    Vec3 o = xL;
    Vec3 prev_ng(0.f);
    bool from_light = true;
    Vec3 last(0.f);
    char types[16];
    int n = 0;
    for (;;) {
      const Vec3 org = from_light ? o : offset_ray_origin(o, prev_ng, d);
      const SurfaceInteraction si = scene_.intersect(org, d, from_light ? 1e-4f : 0.f, kInf);
      from_light = false;
      if (!si.valid) break;
      const Shape& shape = scene_.shapes[size_t(si.shape)];
      if (shape.emitter >= 0) break;
      const BSDFContext ctx = scene_.bsdfs.resolve(shape.bsdf, si);
      if (!ctx.leaf) break;
      const bool chain_vertex = is_chain_shape(si.shape) && is_chain_bsdf(*ctx.leaf);
      if (!chain_vertex) {
        if (ctx.leaf->is_delta() || n == 0) break;  // not a separator, or direct light
        SubpathSample ss;
        for (int a = 0; a < 3; ++a) { ss.xD[a] = si.p[a]; ss.xL[a] = xL[a]; }
        const Vec2 enc = oct_encode(glm::normalize(last - si.p));
        ss.dir[0] = enc.x;
        ss.dir[1] = enc.y;
        char tau[16];
        for (int j = 0; j < n; ++j) tau[j] = types[n - 1 - j];  // x_D -> x_L order
        ss.n = uint8_t(n);
        ss.tau = tau_bits(tau, n);
        ss.flags = 0;
        ss.weight = luminance(flux) / float(count);
        if (std::isfinite(ss.weight) && ss.weight > 0.f) out.push_back(ss);
        break;
      }
      if (n == nmax) break;
      Vec3 wo;
      const float u1 = rng.next_float();
      const Vec2 u2(rng.next_float(), rng.next_float());
      const BSDFSample bs = scene_.bsdfs.sample(ctx, si.wi, u1, u2, wo);
      if (!(bs.pdf > 0.f) || is_black(bs.weight)) break;
      flux *= bs.weight;
      types[n++] = bs.transmission ? 'T' : 'R';
      last = si.p;
      o = si.p;
      prev_ng = si.ng;
      d = wo;
    }
  }
}

}  // namespace mpg
