// Estimator of the light arriving at a separator x_D from a point x_L on a
// light through specular chains (MPG Eq. 1 and 9; SMS, Zeltner et al. 2020):
//
//   f_s(x_D) * kappa * G * L_e / p(x_L) * <1/P(x*|x_D, x_L, n)> / P(n)
//
// with <1/P> the Bernoulli trial count (repeat seed + walk until the same
// solution returns; supplemental Sec. 3.2) and P(n) analytic (Eq. 15).
//
// Seed distributions:
//  - Sms:     one fixed type string tau; x_1 uniform by area on the caster
//             shapes, the rest traced with the letters of tau.
//  - SmsStar: n from a truncated geometric law (a Russian roulette with
//             continuation probability q); x_1 uniform by area on all specular
//             shapes; the type of each vertex drawn by Fresnel (MPG Sec. 5.4).
//
// Ownership (design.md "No double counting"): a path the path tracer samples
// as separator -> specular vertices -> chain emitter is owned by this
// estimator when owns(depth, tau) is true; the path tracer then drops it, or,
// for smooth chains to area lights, keeps its share of a balance heuristic
// (pt_weight; docs/design-notes.md, "Chain paths shared with the path tracer").
#pragma once

#include <array>
#include <functional>
#include <string>
#include <vector>

#include "core/distribution.h"
#include "core/rng.h"
#include "guiding/guiding_state.h"
#include "manifold/walk.h"
#include "render/stats.h"
#include "scene/scene.h"

namespace mpg {

// The Bernoulli estimate of 1/P (supplemental Sec. 3.2): the number K of
// independent trials until `matches()` succeeds, this one included, so
// E[K] = 1/p. At max_trials it stops with capped = true (then E[K] < 1/p: the
// caller counts it).
// One round of the MIS-aware count (ChainEstimator::mis_rounds; design-notes,
// "Chain paths shared with the path tracer"): with probability beta the trial,
// otherwise an immediate success, so P(success) = beta p + 1 - beta.
template <typename U, typename F>
bool mis_round(double beta, U&& uniform, F&& trial) {
  if (beta < 1.0 && !(uniform() < beta)) return true;
  return trial();
}

template <typename F>
int bernoulli_count(F&& matches, int max_trials, bool& capped) {
  capped = false;
  for (int k = 1;; ++k) {
    if (matches()) return k;
    if (k >= max_trials) {
      capped = true;
      return k;
    }
  }
}

// A trial's work in vertex steps (the traced seed and each line-search try)
// under each line-search limit (WalkResult::limited_tries), and the most tries
// one of its walk's later iterations rejected (a limit H keeps its solution iff
// H >= that): for ChainParams::count_limits.
struct TrialTally {
  int later_rejections = 0;
  std::array<uint32_t, kHalvingSlots> steps{};
};
// One round of a Bernoulli count: an immediate success of the MIS-aware coin
// (tried = false), or a trial and whether it found the solution.
struct Round {
  bool tried = false, hit = false;
  TrialTally tally;
};

struct ChainParams {
  enum class Mode { Sms, SmsStar };
  Mode mode = Mode::SmsStar;
  std::string tau = "TT";          // Sms: the fixed chain type
  int max_chain = 6;               // SmsStar: longest chain sampled (and owned)
  float continuation = 0.5f;       // SmsStar: q of P(n) = q^(n-1) (1-q), truncated
  double uniqueness_threshold = 1e-4;
  int max_trials = 100000;
  WalkConfig walk;
  // Manifold path guiding (MPG): learned seed distribution mixed with the
  // initial one by one-sample MIS (Eq. 13), selective activation (Sec. 5.8),
  // recording of sub-path samples for the next training iteration.
  std::shared_ptr<const GuidingState> guide;
  float guide_fraction = 0.5f;     // alpha of Eq. 13
  bool selective = false;          // chains only where the leaf holds unfiltered samples (off: the MPG paper's comparisons)
  // Where a leaf holds samples, the estimator owns a chain to an area light only
  // when the leaf holds a sample of its type (n, tau); the path tracer owns the
  // others whole (design-notes, "Chain types the training never saw").
  bool known_types = false;
  // In pixels of rate 0 (handed to the path tracer), k = handoff_guided extra
  // samples at the path's first separator (0: off): omega_D and the letters
  // drawn from the leaf of (x_D, the light's centre) and traced through the
  // chain, combined with the BSDF-sampled paths by the balance heuristic, k g
  // against b (design-notes, "The guided trace of handed-off pixels").
  int handoff_guided = 0;
  // ... each trace's direction drawn, with this probability, from the leaf's
  // lobes with kappa capped at trace_defensive_kappa (0: never): the broad
  // share covers chain paths of a known type a few lobe widths off the
  // learned lobes, which the BSDF sample would otherwise bring alone at
  // weight ~1 (design-notes, "The guided trace's defensive lobes")
  float trace_defensive = 0.f;
  float trace_defensive_kappa = 400.f;   // (mpg's defaults: guiding.TRACE_DEFENSIVE, _KAPPA)
  // ... and at the separators after a path's first in such pixels, the chain
  // estimator at this rate (0: none, the path tracer's there too). The
  // hand-off is learned for the first separator; a later one is reached by
  // few samples, whose chain paths the path tracer finds rarely and, after
  // the roulette, with a throughput near 1 (double_slabs' handed pixels).
  float handoff_deep = 0.f;
  bool record = false;             // store SubpathSamples in Stats::subpaths
  bool count_limits = false;       // Stats::limit_m2 / limit_steps (mpg's training, step_halvings=auto)
  bool product = false;            // product sampling with the separator's BSDF (MPG Eq. 14)
  bool guide_n = true, guide_tau = true, guide_dir = true;  // ablation switches
  // Share the chain paths the path tracer can also reach (smooth chains to area
  // lights) by the balance heuristic instead of giving them whole to the estimator
  // (docs/design-notes.md, "Chain paths shared with the path tracer").
  bool mis = true;
  // ... and count the roulette's rate q (chain_rate below, or the pixel's) in
  // the estimator's density: the balance heuristic between the path tracer (b)
  // and "run the estimator w.p. q, then find the chain" (q a P), i.e. b / q in
  // place of b on both sides (design-notes, "The rate in the balance heuristic").
  bool mis_rate = true;
  // Probability that a separator runs the estimator at all (Russian roulette on
  // the chain estimate, weighted 1/q; design-notes "Chain estimates by roulette").
  float chain_rate = 1.0f;
};

// A leaf already looked up for a pair (x_D, x_L) (active_for), so that
// pt_weight at the same pair does not descend the tree again.
struct LeafQuery {
  bool done = false;
  const ChainDistribution* leaf = nullptr;
};

class ChainEstimator {
 public:
  ChainEstimator(const Scene& scene, ChainParams p);

  bool active() const { return active_; }
  const Scene& scene() const { return scene_; }
  // A point or spot light among the chain lights: the path tracer never hits
  // it, so rate 0 (the path tracer alone) would lose its light through chains.
  bool has_delta_lights() const { return has_delta_lights_; }
  // The roulette's rate at the pixel being rendered: its map value when the
  // pass has a map (mpg's learned rates; 0: handed to the path tracer), the
  // estimator's chain_rate otherwise. path.cpp's roulette, the weights
  // (rate_b) and the stats all take q from here.
  float rate_at(const Stats& st) const { return st.pixel_chain_rate >= 0.f ? st.pixel_chain_rate : p_.chain_rate; }
  // Does the estimator produce chains of type `tau` at a separator of loop depth
  // `depth` (path tracer's convention, camera hit = 0) under `max_depth`?
  bool owns(uint32_t depth, uint32_t max_depth, const std::string& tau) const;
  // With selective activation, ownership also depends on the configuration.
  // With known_types, also on the type of the chain (letters `tau`) to an
  // area light at x_L. (`st`: its leaf query counts in guide_ns, as the
  // estimator's own. `q`: the leaf it looked up, if it did, for pt_weight at
  // the same x_D, x_L.)
  bool active_for(const Vec3& xD, const Vec3& xL, const std::string& tau, Stats* st = nullptr,
                  LeafQuery* q = nullptr) const {
    if (!(p_.guide && p_.guide->valid() && (p_.selective || p_.known_types))) return true;
    const ChainDistribution* leaf = guide_at(xD, xL, st);
    if (q) *q = LeafQuery{true, leaf};
    if (!leaf) return !p_.selective;
    return !p_.known_types || leaf->has_type(int(tau.size()), tau_bits(tau.data(), int(tau.size())));
  }
  // A chain from x_D (normal nD) to the point xP (the camera's pinhole, for
  // the light tracer) through the chain shapes, as sms_star seeds it (x_1
  // uniform on the chain shapes, letters by Fresnel, no guide), its length m
  // from the initial law truncated at mmax (SmsStar mode only). On success:
  // the chain (x_D -> xP order), m, and the weight kappa G K / P(m) of the
  // radiance leaving x_D toward chain.v[0] as it arrives at xP: kappa the
  // lobes' weights with the radiance scaling toward xP, G = |d omega_P / dA_D|
  // (geometry_point), K the Bernoulli count of 1/P (supplemental Sec. 3.2).
  // The last segment's visibility is the caller's.
  bool connect_point(const DVec3& xD, const DVec3& nD, const DVec3& xP, int mmax, PCG32& rng, Stats& st,
                     ManifoldChain& chain, Color& weight) const;
  bool sms_star_mode() const { return p_.mode == ChainParams::Mode::SmsStar; }
  int max_chain() const { return p_.max_chain; }
  // The longest chain estimated at a separator of loop depth `depth` (0: the
  // camera's first hit) under max_depth (-1 as uint32: unbounded).
  int max_chain_len(uint32_t depth, uint32_t max_depth) const { return max_len(depth, max_depth); }
  // Every chain shape smooth (its BSDF a chain node at glossy threshold 0: no
  // glossy chain vertex) and without a normal map, as the light tracer needs
  // (integrators/light_trace.h).
  bool chain_shapes_smooth() const { return chain_shapes_smooth_; }
  // Rough interfaces with alpha below this are chain vertices (WalkParams).
  float glossy_threshold() const { return p_.walk.glossy_threshold; }
  // Is shape `s` a surface the walk accepts as a specular vertex?
  bool is_chain_shape(int s) const { return specular_shape_[size_t(s)] != 0; }
  // Are all of a traced seed's vertices on chain shapes? (trace_seed checks the
  // BSDFs only; a glossy receiver or a specular emitter shape is the path
  // tracer's separator or end, never a chain vertex.)
  bool on_chain_shapes(const ManifoldChain& c) const {
    for (const ManifoldVertex& v : c.v)
      if (!is_chain_shape(v.shape)) return false;
    return true;
  }
  // Is this resolved BSDF a chain vertex (smooth, or glossy below the
  // threshold)? Such vertices are not separators for the path tracer.
  bool is_chain_bsdf(const BSDF& b) const { return chain_leaf(b, p_.walk.glossy_threshold); }
  // The same test for any threshold (the light tracer's glossy mode, which
  // runs without an estimator): smooth, or rough below glossy_threshold.
  static bool chain_leaf(const BSDF& b, float glossy_threshold) {
    if (b.type == BSDFType::Dielectric || b.type == BSDFType::Conductor) return true;
    return (b.type == BSDFType::RoughDielectric || b.type == BSDFType::RoughConductor) &&
           std::max(b.mf.ax, b.mf.ay) < glossy_threshold;
  }

  // The glints: the small area lights seen from the camera through chain
  // vertices only (docs/design-notes.md, "Glints"). A light whose angular
  // size is below a few pixels is a glint in the glass: the path tracer finds
  // it only where a camera sample lands in its tiny image (variance L^2 c for
  // a pixel it covers a fraction c of), so these paths, camera -> 1..mmax
  // chain vertices -> such a light, are this estimator's instead and the path
  // tracer drops them (path.cpp). Per camera sample: x_L uniform by area on
  // an owned light, the sample's own camera ray as the seed (letters by
  // Fresnel), a walk with the pinhole and x_L fixed, and where the solution
  // is seen in the sample's pixel, the pixel's value
  //   Le kappa G K / (p(x_L) A_pix cos^3 theta)                      (1)
  // G = |d omega_camera / dA_L| (geometry_area with x_D the pinhole), K the
  // Bernoulli count of 1/P over seeds from the same pixel (supplemental Sec.
  // 3.2), A_pix the pixel's area on the film at unit distance (a box filter
  // of one pixel: the pixel value is the mean radiance over its area, dA =
  // d omega / cos^3 theta). One walk per chain length m whose seed ray after
  // vertex m passes within `capture` of the light's centre (a part of the
  // seed process, which the trials repeat: a solution's own ray passes, so
  // every solution keeps P > 0).
  struct GlintLights {
    int mmax = 0;                 // longest chain (camera side: m + 1 segments <= max_depth)
    std::vector<int> emitters;    // the owned lights
    std::vector<char> owned;      // emitter index -> owned
    std::vector<DVec3> centre;    // per owned light: its bounding sphere's centre
    std::vector<double> capture;  // ... and the seed's capture radius around it
    DiscreteDistribution dist;    // by power
    Mat4 to_local{1.f};
    DVec3 cam_fwd{0.0, 0.0, 1.0};
    double a_pix = 0.0;
    bool usable() const { return mmax > 0 && !emitters.empty(); }
    bool owns(int e) const { return e >= 0 && size_t(e) < owned.size() && owned[size_t(e)] != 0; }
  };
  // The area chain lights whose angular diameter, seen over the path camera ->
  // chain shapes' centre -> light, is below max_pixels pixels (none with a
  // filter other than a one-pixel box, or max_pixels <= 0).
  GlintLights glint_lights(float max_pixels, int max_depth) const;
  // (1) for one camera sample: its ray (o, d) from film pixel (fx, fy) and
  // first hit si. 0 where the hit is not a chain shape.
  Color glint(const GlintLights& gl, const Vec3& o, const Vec3& d, const SurfaceInteraction& si, int fx, int fy,
              PCG32& rng, Stats& st) const;

  // Photon initialisation (MPG supplemental Sec. 2): trace `count` photons from
  // the chain emitters through chain vertices; each that lands on a separator
  // after 1..max_chain chain vertices becomes a sub-path sample (x_D = landing
  // point, x_L = emission point, omega_D toward the last chain vertex, n, tau
  // in x_D -> x_L order) weighted by its flux (supplemental Eq. 4).
  // Deterministic for a given seed: traced on `threads` threads (0: all
  // cores), the same buffer whatever their count. Returns the number of
  // photons traced. begin/end (end 0: count): only photons [begin, end) of
  // those `count`, weighted as in the whole trace (flux / count), so the
  // buffers of consecutive ranges appended in order are the whole trace's
  // buffer, sample for sample (mpg.guiding's photon guide, grown over the
  // training's guide builds).
  uint64_t trace_photons(uint64_t count, uint64_t seed, std::vector<SubpathSample>& out, int threads = 0,
                         uint64_t begin = 0, uint64_t end = 0) const;
  // (trace_photons' photons [begin, end), appended to out)
  void trace_photon_range(uint64_t begin, uint64_t end, uint64_t count, uint64_t seed,
                          std::vector<SubpathSample>& out) const;

  // The path tracer's weight for a path it traced from the separator `sep`
  // (resolved BSDF `sep_ctx`, loop depth `sep_depth`) through the chain vertices
  // `verts` (letters `tau`) to the emitter hit `light`, when owns() and
  // active_for() hold: an unbiased estimate of b / (a P + b), the path
  // tracer's balance-heuristic weight (docs/design-notes.md, "Chain paths shared
  // with the path tracer"), or 0 when the estimator takes the path whole (mis
  // off, glossy or normal-mapped vertices, a degenerate chain). `unit`: the
  // path's value before the weight (count_limits tallies unit x weight).
  float pt_weight(const SurfaceInteraction& sep, const BSDFContext& sep_ctx, uint32_t sep_depth,
                  uint32_t max_depth, const SurfaceInteraction* verts, const std::string& tau,
                  const SurfaceInteraction& light, PCG32& rng, Stats& st,
                  const Color& unit = Color(0.f), const LeafQuery* known = nullptr,
                  bool* whole = nullptr) const;

  // handoff_guided (rate-0 pixels): does the technique run here?
  bool guided_trace_on() const { return p_.handoff_guided > 0 && p_.guide && p_.guide->valid() && active_; }
  using TraceSample = mpg::TraceSample;   // (render/stats.h)
  // k samples at the separator `si` (k: the pixel's count, Stats::pixel_trace_k,
  // handoff_guided by default): the light each finds through the chain,
  // weighted by the multi-sample balance heuristic, i.e. f / (b + k g) each
  // against the path tracer's BSDF sampling (f_s |cos| included; times the
  // path's throughput by the caller).
  Color guided_trace(const SurfaceInteraction& si, const BSDFContext& ctx, uint32_t depth, uint32_t max_depth,
                     int k, PCG32& rng, Stats& st) const;
  // One of guided_trace's traces, unweighted (f, b, g; TraceSample::weighted).
  TraceSample guided_trace_one(const SurfaceInteraction& si, const BSDFContext& ctx, uint32_t depth,
                               uint32_t max_depth, PCG32& rng, Stats& st) const;
  // The densities b (path tracer) and g (one trace) of a path the path tracer
  // traced from the separator along `wD` (its BSDF sample's direction, the one
  // the density is of) through the chain vertices `verts` (letters `tau`) to
  // the emitter hit `light`; false where the guided trace cannot produce the
  // path (the path tracer's weight is 1 there).
  bool guided_trace_densities(const SurfaceInteraction& sep, const BSDFContext& sep_ctx, uint32_t sep_depth,
                              uint32_t max_depth, const Vec3& wD, const SurfaceInteraction* verts,
                              const std::string& tau, const SurfaceInteraction& light, Stats& st,
                              double& b, double& g) const;
  // ... and its weight b / (b + k g) against k traces (1 where false above).
  static float guided_trace_pt_weight(bool shared, double b, double g, int k);
  int handoff_guided() const { return p_.handoff_guided; }
  float handoff_deep() const { return p_.handoff_deep; }

  // Test entry point: the densities a (estimator, without P) and b (path
  // tracer) of one path as each side computes them. The path tracer's path
  // runs from the camera ray (o, d) to its first hit x_D, then along omega_D
  // through the letters of `tau` (ideal R/T) to an emitter; the estimator's
  // chain is a walk from `seed_dir` at x_D to the same x_L. False when either
  // side fails or the walk finds another solution.
  bool mis_pair(const Vec3& o, const Vec3& d, const Vec3& omega_D, const Vec3& seed_dir,
                const std::string& tau, double ab[4]) const;

  // Contribution at x_D (already multiplied by f_s * |cos|); `wi` toward the camera.
  // `beta`: the path's throughput the caller multiplies the estimate by (count_limits
  // tallies the sample's part, beta x estimate).
  // `dens` (training's trace records, Stats::sample_tail): where the estimate
  // found a chain path to an area light through delta vertices (at most
  // kMaxN) after a reflection at x_D (ok; others are left out, and the path
  // tracer's side leaves out the same), the path's densities as the rate-0
  // forms see it: unit = f_s |cos| kappa Le (the path's value per solid angle
  // at x_D, throughput not included), b = the path tracer's solid-angle
  // density of it (pdf_bsdf(omega_D) times its letters' probabilities as it
  // draws them), g = one guided trace's (want_g: the first separator; 0
  // otherwise). With the path tracer's roulette survival p along the chain,
  // its part of form k's second moment is unit (b/p + k g) / (b + k g)^2 per
  // unit (Stats::sample_tail).
  // For the path tracer's roulette along the path (PathIntegrator::
  // chain_survival): its BSDF sample's weight at x_D (f_s |cos| / pdf), and
  // at each of the n chain vertices its weight and eta as it draws the letter.
  struct PathDensities {
    bool want_g = false;
    bool ok = false;
    Color unit{0.f};
    double b = 0.0, g = 0.0;
    int n = 0;
    Color sep_weight{0.f};
    std::array<Color, ChainDistribution::kMaxN> w{};
    std::array<float, ChainDistribution::kMaxN> eta{};
  };
  Color estimate(const SurfaceInteraction& si, const BSDFContext& ctx, uint32_t depth,
                 uint32_t max_depth, PCG32& rng, Stats& st, const Color& beta = Color(1.f),
                 PathDensities* dens = nullptr) const;

 private:
  struct LightPoint {
    DVec3 p{0.0}, n{0.0};
    Color value{0.f};   // area: radiance; point/spot: intensity toward the chain handled later
    double pdf = 0.0;   // area density incl. selection (area) or selection probability (point/spot)
    bool point = false;
    int emitter = -1;
  };
  bool sample_light(PCG32& rng, LightPoint& lp) const;
  int max_len(uint32_t depth, uint32_t max_depth) const;
  double pmf_n(int n, int nmax) const;
  int sample_n(float u, int nmax) const;
  // P(n) of the mixture of the initial law and the learned one (truncated at nmax).
  double pmf_n_mix(int n, int nmax, const ChainDistribution* d, double learned_mass) const;
  // The initial law's seed direction: toward x_1 uniform by area on the
  // specular shapes (false: x_1 at x_D).
  bool initial_seed_dir(const DVec3& xD, PCG32& rng, DVec3& dir) const;
  // A seed traced from x_D along dir with the letters tau, on the chain shapes
  // (failures counted).
  bool trace_lettered_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir, const std::string& tau,
                           const std::vector<Vec2>& offsets, ManifoldChain& chain, Stats& st) const;
  // The walk from a traced seed to an admissible chain (its steps and failures counted).
  bool solve_seed(ManifoldChain& chain, int n, Stats& st, TrialTally* tally) const;
  // n seed vertices traced from x_D along dir, the letters by Fresnel at
  // dielectrics (want_tau: stop, unsuccessful, at the first other letter).
  bool trace_fresnel_seed(const DVec3& xD, const DVec3& nD, const DVec3& dir, int n,
                          const std::vector<Vec2>& offsets, PCG32& rng, ManifoldChain& chain,
                          std::string& tau, Stats& st, const std::string* want_tau) const;
  // One trial: seed + walk. Fills chain and tau on success. With want_tau (a
  // Bernoulli trial, which hits only a chain of those letters) the trial stops,
  // unsuccessful, as soon as its seed's letters differ: the walk keeps them.
  bool trial(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
             const std::vector<Vec2>& offsets, const ChainDistribution* guide, PCG32& rng,
             ManifoldChain& chain, std::string& tau, Stats& st,
             TrialTally* tally = nullptr, const std::string* want_tau = nullptr) const;
  // A glint seed continued from the camera ray's first hit: up to m chain
  // vertices, letters by Fresnel (want_tau: stop at the first other letter);
  // dirs[i] the ray leaving vertex i. Returns the vertices traced.
  int glint_seed(const DVec3& o, const SurfaceInteraction& first, const Vec3& d, int m,
                 PCG32& rng, ManifoldChain& chain, std::string& tau, std::vector<DVec3>& dirs,
                 const std::string* want_tau, Stats& st) const;
  // (eta2: if given, the product of the transmissions' (eta_i / eta_t)^2 from x_D toward x_L)
  Color kappa(const ManifoldChain& chain, const std::string& tau, bool flux = false, double* eta2 = nullptr) const;
  // The leaf of (x_D, x_L), or null (no guide, or an empty leaf).
  const ChainDistribution* guide_at(const Vec3& xD, const Vec3& xL, Stats* st) const;
  // P(n) of the estimator at a leaf (Eq. 13's mixture; the initial law without a leaf).
  double pn_at(const ChainDistribution* guide, int n, int nmax) const;
  // Probability that the path tracer picks the letters of `tau` at the chain's
  // vertices (Fresnel at dielectrics, 1 at conductors); -1 when a vertex is
  // glossy or normal-mapped (no sharing there).
  double pt_letters_pdf(const ManifoldChain& c, const std::string& tau) const;
  // The path tracer's draw of letter `letter` ('R'/'T') at chain vertex `v`
  // (its BSDF resolved there, a delta lobe forced): false where it cannot draw
  // it (not delta, null, the other letter); bs: its probability, weight, eta.
  bool pt_letter(const SurfaceInteraction& v, char letter, BSDFSample& bs) const;
  // b: the path tracer's density of a converged chain per unit area at x_L,
  // pdf_bsdf(omega_D) * pt_letters_pdf * G; 0 when the path is not shared.
  double pt_density(const ManifoldChain& c, const std::string& tau, const BSDFContext& ctx,
                    const Vec3& wi, double G) const;
  // The path tracer's density as the balance heuristic weighs it against the
  // estimator's a P: b, or with mis_rate b / q, q the roulette's rate at this
  // pixel (path.cpp takes it the same way), so that the weights are those of
  // the path tracer against "run the estimator w.p. q, then find the chain".
  double rate_b(double b, const Stats& st) const {
    if (!p_.mis_rate || !(b > 0.0)) return b;
    const double q = double(rate_at(st));
    return q > 0.0 && q < 1.0 ? b / q : b;
  }
  // The path tracer's side: chain, light point and densities of a traced path.
  // Returns 0: not shared (the estimator takes it whole), 1: the estimator
  // cannot produce it (the path tracer keeps it whole), 2: shared (a, b set).
  int pt_densities(const SurfaceInteraction& sep, const BSDFContext& sep_ctx, uint32_t sep_depth,
                    uint32_t max_depth, const SurfaceInteraction* verts, const std::string& tau,
                    const SurfaceInteraction& light, ManifoldChain& c, LightPoint& lp,
                    const ChainDistribution*& guide, double& a, double& b, Stats* st = nullptr,
                    const LeafQuery* known = nullptr) const;
  // Density per unit area of x_L on chain light k (area light): selection by power times 1/area.
  double area_light_pdf(size_t k) const;
  // The guided trace's density of a path (n, letters `bits`, omega_D) at x_D to
  // chain light k: P(k) P_e(n) P_e(tau | n) pdf(omega_D), the leaf at (x_D,
  // light_centre_[k]); 0 where it cannot draw it.
  double guided_trace_pdf(const Vec3& xD, size_t k, int n, uint16_t bits, const Vec3& wD, int nmax,
                          Stats* st) const;
  // ... its product at a leaf already looked up (n within the limit).
  // (lobes: where to count the lobes pdf_dir visits, Stats::trace_lobes / trace_pt_lobes)
  double leaf_trace_pdf(const ChainDistribution& leaf, size_t k, int n, uint16_t bits, const Vec3& xD,
                        const Vec3& wD, uint64_t* lobes = nullptr) const;
  // K' of the MIS-aware Bernoulli process: each round, with probability beta a
  // trial that succeeds iff it finds (tau*, omega*), otherwise an immediate
  // success; E[K'] = 1 / (beta P + 1 - beta). beta = 1: SMS's K, E = 1/P.
  // One round of it (tally: fill the trial's TrialTally).
  Round round(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
              const std::vector<Vec2>& offsets, const ChainDistribution* seed_guide,
              const std::string& tau_star, const DVec3& w_star, double beta, PCG32& rng, Stats& st,
              bool tally) const;
  int mis_rounds(const DVec3& xD, const DVec3& nD, const LightPoint& lp, int n,
                 const std::vector<Vec2>& offsets, const ChainDistribution* seed_guide,
                 const std::string& tau_star, const DVec3& w_star, double beta, PCG32& rng,
                 Stats& st, bool& capped, std::vector<Round>* rounds = nullptr) const;
  // count_limits: the estimate (value X, K rounds, its first trial and rounds)
  // as it would have been under each line-search limit (Stats::limit_m2,
  // limit_steps; pt: the path tracer's share of a shared path, limit_pt_*),
  // running further rounds (`more`, given scratch stats: they stay out of the
  // pass's) where a limit's count would go on past K.
  void tally_limits(const TrialTally& first, const std::vector<Round>* rounds, const Color& X, int K,
                    double q, const std::function<Round(Stats&)>& more, Stats& st, bool pt = false) const;

  const Scene& scene_;
  ChainParams p_;
  ManifoldWalk walk_;
  bool active_ = false;
  std::vector<char> specular_shape_;
  std::vector<int> seed_shapes_;     // shapes seeds are drawn on
  DiscreteDistribution seed_dist_;   // by area
  std::vector<int> chain_lights_;    // emitters used as x_L
  bool has_delta_lights_ = false;
  bool chain_shapes_smooth_ = true;
  DiscreteDistribution light_dist_;  // by power
  std::vector<int> light_index_;     // emitter -> index in chain_lights_, or -1
  std::vector<Vec3> light_centre_;   // per chain light: its centroid (area lights; the guided trace's leaf)
};

}  // namespace mpg
