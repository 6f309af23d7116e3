// Per-pass statistics, accumulated per thread and merged.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "core/math.h"
#include "guiding/subpath_sample.h"
#include "manifold/walk.h"

namespace mpg {

// One guided trace of a handed-off pixel (ChainEstimator::guided_trace_one):
// f = the light it found through the chain times f_s |cos| and the letters'
// weights (0: no hit; times the path's throughput where recorded), b and g the
// path tracer's and the trace's densities of that path.
struct TraceSample {
  Color f{0.f};
  double b = 0.0, g = 0.0;
  bool tail_ok = false;   // a reflection at the separator (Stats::sample_tail covers its path)
  // its share with k traces, by the multi-sample balance heuristic: f / (b + k g)
  Color weighted(int k) const {
    // in double: with b = 0 and a tiny g the float of 1 / (b + k g) would
    // overflow, and inf x a zero channel is NaN (the whole sample rejected)
    if (is_black(f) || !(g > 0.0) || k < 1 || !std::isfinite(b + g)) return Color(0.f);
    const double s = 1.0 / (std::max(b, 0.0) + double(k) * g);
    Color out(0.f);
    for (int ch = 0; ch < 3; ++ch) {
      const double v = double(f[ch]) * s;
      if (!std::isfinite(v) || v > 3.0e38) return Color(0.f);
      out[ch] = float(v);
    }
    return out;
  }
};

struct Stats {
  // The pass's cancel flag (set by the render worker, null elsewhere): long
  // loops inside one sample (Bernoulli trials) poll it, so that a cancelled
  // pass, which is dropped anyway, stops within one trial instead of one sample
  // (a sample can run up to max_trials walks, seconds with long chains).
  const std::atomic<bool>* cancel = nullptr;
  bool cancelled() const { return cancel && cancel->load(std::memory_order_relaxed); }
  // Per-pixel context set by the render worker (not merged): the pixel's chain
  // rate from the pass's map (< 0: no map, the estimator's own rate; 0: the
  // path tracer takes the chains' light whole in this pixel, no chain
  // estimates), and the running sum over the pixel's samples of
  // sum_j X_j^2 / q, X_j a chain estimate run at rate q (unweighted, mean over
  // RGB): an unbiased estimate of the second moment the roulette multiplies by
  // (1/q - 1) (design-notes "Chain rates per pixel").
  float pixel_chain_rate = -1.f;
  // Set by the path tracer before each chain estimate (not merged): the
  // estimate leaves out point and spot lights (a depth-0 separator whose
  // chains to them the light tracer brings; integrators/light_trace.h).
  bool chain_skip_delta_lights = false;
  // ... and area lights too (LightTracer::traces_area)
  bool chain_skip_area_lights = false;
  // With PassConfig::record_classes (set by the render worker): the camera
  // sample's value split by where it entered (reset per camera sample): chain
  // estimates (X / q), the path tracer's shares of shared chain paths, the
  // handed-off pixels' traced chain light (the guided traces and the path
  // tracer's weights against them), chain paths the path tracer kept whole in
  // pixels of rate 0 (untraced), and elsewhere because the estimator does not
  // take them: a type their leaf never saw (known_types), no leaf with
  // unfiltered samples (selective activation), not owned (a length or light
  // the estimator does not produce); the worker adds the light seen through
  // delta scattering only, the rest and the glints (bench/error_classes.py)
  static constexpr int kClasses = 10;
  enum Class { kClassChain = 0, kClassShared, kClassTraced, kClassHanded, kClassUnseen, kClassInactive,
               kClassUnowned, kClassDelta, kClassOther, kClassGlints };
  bool record_classes = false;
  Color sample_class[kClasses] = {};
  void add_class(int c, const Color& v) {
    if (record_classes) sample_class[c] += v;
  }
  // PassConfig::guided_trace_map at the pixel: its count of guided traces in
  // rate-0 pixels (-1: no map, the integrator's handoff_guided)
  int pixel_trace_k = -1;
  // PassConfig::deep_rate_map at the pixel: the chain rate at a rate-0
  // pixel's separators after the first (-1: no map, ChainParams::handoff_deep)
  float pixel_deep_rate = -1.f;
  double pixel_chain_m2 = 0.0;
  // Per camera sample (reset by the render worker): what the sample's value
  // would change by if the path tracer kept the chain paths whole and no chain
  // estimate ran -- + the owned light's share the path tracer dropped, - the
  // chain estimates added. Training passes record the value this gives, the
  // "path tracer alone" estimate of the same pixel, to decide where rate 0 pays
  // (design-notes "Handing pixels to the path tracer").
  Color sample_alt_delta{0.f};
  bool sample_owned_hit = false;   // ... and whether the path tracer found owned light in the sample
  // With record_trace (set by the render worker in training passes that
  // record costs): what the pixel would get at rate 0 with the guided trace
  // of handed-off pixels, for k = 1, 2, 4, 8 traces (kTraceKs counts, k = 2^i),
  // from the "path tracer alone" value above. Per k, the change of the path
  // tracer's own chain paths after the first separator, (w_k - 1) times each
  // (w_k its balance weight against k traces); and two traces drawn at that
  // separator (throughput included), from which the render worker forms each
  // k's value and the variance of one trace (design-notes "The rates choose
  // the guided trace"). Whether the path tracer or a trace found chain light,
  // and the traces' rays (counted in `rays` too).
  static constexpr int kTraceKs = 4;
  static constexpr int kTraceRecorded = 2;   // (render.cpp forms the values from exactly two)
  static constexpr int kTraceRecordEvery = 4;   // samples per one that records (render.cpp)
  // training passes of a branching integrator: samples per one that also records
  // branched and plain delta paths, if its own path saw a delta vertex
  // (PassResult::bdelta_*; render.cpp)
  static constexpr int kBranchRecordEvery = 8;
  bool record_trace = false;
  Color sample_trace_hits_delta[kTraceKs] = {};
  TraceSample sample_traces[kTraceRecorded];
  bool sample_trace_hit = false;
  bool sample_trace_recorded = false;   // ... the sample's path could record them (path.cpp's trace_alt)
  uint64_t trace_rays = 0;
  // ... the lobes the traces' densities visited (ChainDistribution::pdf_dir,
  // one dot product each: a leaf of 3 000 lobes costs ~20 rays), and those of
  // the path tracer's weights against them (trace_pt_lobes); counted always
  uint64_t trace_lobes = 0, trace_pt_lobes = 0;
  // ... and, in the same recorded samples, the rate-0 forms' second moments of
  // the chain paths as the chains sample them (design-notes "The traces'
  // tails"): sum over the sample's chain-path values Y (chain estimates as
  // they enter the sample, X / q, and the path tracer's shares of shared
  // chain paths) of Y times V_k = F (b/p + k g) / (b + k g)^2, the path's
  // part of form k's second moment per unit of its integrand F (b the path
  // tracer's density, p its roulette's survival after the separator, k g the
  // traces'; index 0: the path tracer alone, V = F / (b p); index f + 1: k =
  // 2^f traces; mean over RGB). E[sum Y V_k] = the integral of F^2 (b/p + k
  // g) / (b + k g)^2 over the chain paths, whichever technique found them, so
  // the rare paths the path tracer and the traces seldom reach (their tails)
  // count at the chains' rate. sample_chain_part: the sum of the Y.
  // The same moments as the records see them (render.cpp's trace_seen):
  // sample_seen_P[f], the sample's chain paths the path tracer found, as
  // valued by form f (the path tracer alone's c; c w_k with k traces), whose
  // square and the recorded traces' give each form's sum of squared path
  // values. Both over the same paths: a reflection at the separator and delta
  // chain vertices (TraceSample::tail_ok; estimate()'s PathDensities).
  double sample_tail[kTraceKs + 1] = {};
  Color sample_chain_part{0.f};
  Color sample_seen_P[kTraceKs + 1] = {};
  // Per camera sample: the part of its value from the light seen through delta
  // scattering only (PathParams::CameraDelta), recorded in every sample. With
  // split_delta (set per pixel by the render worker when its delta-split count
  // k > 1) that part is left out of Li's value, and the worker averages it with
  // k - 1 extra camera paths of that light alone (design-notes "Splitting the
  // light seen in the glass").
  Color sample_delta_L{0.f};
  bool split_delta = false;
  // Set by the render worker per pixel (not merged): its film pixel, which
  // the glints' Bernoulli trials draw their seeds from; and per camera sample
  // the glints' part of Li's value (Integrator::Li; a class of its own).
  int film_x = -1, film_y = -1;
  Color sample_glint{0.f};
  uint64_t samples = 0;
  uint64_t camera_rays = 0;
  uint64_t rays = 0;           // intersection queries
  uint64_t shadow_rays = 0;
  uint64_t rejected_nan = 0;   // samples with NaN, dropped (contribute zero)
  uint64_t rejected_inf = 0;
  uint64_t rejected_negative = 0;
  uint64_t depth_capped = 0;   // paths stopped by the hard bounce cap
  uint64_t path_vertices = 0;
  uint64_t delta_prefix_rays = 0;    // rays traced after delta scattering only (camera rays not counted)
  uint64_t delta_split_paths = 0;    // extra camera paths of the light seen through delta scattering
  uint64_t delta_branches = 0;       // vertices where such a path followed both delta lobes (delta_branch)
  uint64_t pixel_split_samples = 0;  // extra camera samples of the pixel split (PassConfig::pixel_split_map)
  // specular chains (sms, sms_star)
  uint64_t chain_estimates = 0;      // separators where a chain was attempted
  uint64_t chain_converged = 0;      // first trials that converged
  uint64_t chain_contributions = 0;  // non-zero chain contributions
  uint64_t bernoulli_trials = 0;     // extra trials spent estimating 1/P
  uint64_t bernoulli_capped = 0;     // estimates stopped by max_trials (biased, counted)
  uint64_t owned_dropped = 0;        // path-traced chain paths dropped (owned by the estimator)
  uint64_t owned_shared = 0;         // path-traced chain paths kept with an MIS weight < 1
  uint64_t chain_ns = 0;             // time in chain estimation (summed over threads)
  uint64_t bernoulli_ns = 0;         // of which: the Bernoulli trials estimating 1/P
  uint64_t chain_unknown_type = 0;   // first trials whose type the leaf never saw (known_types): the path tracer's
  // Guiding (STree query, sampling n, tau, omega from a leaf), in the estimator
  // and in the path tracer's MIS side and selective activation; one call in 8
  // timed and counted 8 times (chain_estimator.cpp). guide_clock_ns: the
  // clock's own share of those intervals, which to_map's guide_ns leaves out
  // (guide_ns_raw keeps it).
  uint64_t guide_ns = 0;
  uint64_t guide_clock_ns = 0;
  uint64_t walk_steps = 0;           // manifold-walk work: traced vertices + those of accepted iterations, all trials
  uint64_t walk_reprojections = 0;   // line-search tries of the walks (each reprojects the chain)
  uint64_t walk_off_surface = 0;     // of which: the moved chain did not land on its shapes
  uint64_t chain_steps = 0;          // of which: inside chain estimates (not the path tracer's MIS rounds)
  // ChainParams::count_limits (mpg's training under step_halvings=auto): the
  // chain estimates' second moment, sum of X^2 / q (mean over RGB; q the
  // roulette's rate), and, for each line-search limit H (slot H = 0..10;
  // kFullSearch: the walk as configured), the same sum and the estimates' walk
  // steps had the walks run under that limit (ChainEstimator::tally_limits).
  // The same for the path tracer's shares of shared chain paths (pt_weight:
  // b / (a P + b) moves with the estimator's P), at full weight (no rate).
  double chain_m2 = 0.0, pt_shared_m2 = 0.0;
  std::array<double, kHalvingSlots> limit_m2{}, limit_steps{}, limit_pt_m2{}, limit_pt_steps{};
  std::array<uint64_t, kHalvingSlots> limit_censored{};  // counts whose extra rounds hit their cap
  std::array<uint64_t, 11> walk_failures{};  // by WalkFailure
  // guiding (mpg)
  uint64_t guided_trials = 0;        // trials whose seed came from the learned distribution
  uint64_t trials_tau_cut = 0;       // Bernoulli trials stopped early: their letters differ
  uint64_t chain_inactive = 0;       // separators skipped by selective activation
  uint64_t chain_skipped = 0;        // separators skipped by the roulette (chain_rate < 1)
  uint64_t chain_handed = 0;         // separators in pixels of rate 0 (the path tracer's light whole)
  uint64_t chain_deep = 0;           // separators after a path's first in pixels of rate 0, at handoff_deep's rate or the pixel's deep_rate_map (not in chain_handed)
  // light tracing (integrators/light_trace.h)
  uint64_t chain_lt_skipped = 0;     // chain estimates whose point/spot light the light tracer takes (value 0)
  uint64_t lt_photons = 0, lt_rays = 0, lt_splats = 0;
  uint64_t lt_chain_tries = 0, lt_chain_splats = 0;   // connections to the camera through glass (light_trace_through)
  uint64_t lt_rejected = 0;          // splats not finite or negative (dropped, counted)
  // glints (ChainEstimator::glint): camera samples whose first hit was a chain
  // shape, walks run, estimates found in their pixel, Bernoulli trials,
  // non-finite estimates dropped, path-tracer light hits the glints bring
  uint64_t glint_seeds = 0, glint_walks = 0, glint_found = 0, glint_trials = 0, glint_rejected = 0;
  uint64_t glint_capped = 0;         // Bernoulli counts stopped at max_trials (K then biased low)
  uint64_t glint_pt_dropped = 0;
  uint64_t lt_pt_dropped = 0;        // path-tracer contributions (light hits; glossy mode: NEE too) whose path the photons bring
  uint64_t guided_traces = 0;        // handoff_guided: traces drawn from a leaf in rate-0 pixels (and training's records)
  uint64_t guided_traces_defensive = 0;   // ... of which drawn from the defensive lobes (trace_defensive)
  uint64_t guided_trace_hits = 0;    // ... that reached their light through the drawn letters
  std::vector<SubpathSample> subpaths;  // recorded in training passes
  // the largest chain estimate (luminance) and its factors: where the heavy tail comes from
  double max_chain_value = 0.0, max_chain_K = 0.0, max_chain_G = 0.0, max_chain_pn = 0.0,
         max_chain_n = 0.0, max_chain_guided = 0.0, max_chain_rate = 0.0;

  void merge(const Stats& o) {
    samples += o.samples; camera_rays += o.camera_rays; rays += o.rays;
    shadow_rays += o.shadow_rays; rejected_nan += o.rejected_nan; rejected_inf += o.rejected_inf;
    rejected_negative += o.rejected_negative; depth_capped += o.depth_capped;
    path_vertices += o.path_vertices;
    delta_prefix_rays += o.delta_prefix_rays; delta_split_paths += o.delta_split_paths;
    delta_branches += o.delta_branches;
    pixel_split_samples += o.pixel_split_samples;
    chain_estimates += o.chain_estimates; chain_converged += o.chain_converged;
    chain_contributions += o.chain_contributions; bernoulli_trials += o.bernoulli_trials;
    bernoulli_capped += o.bernoulli_capped; owned_dropped += o.owned_dropped; owned_shared += o.owned_shared; chain_ns += o.chain_ns;
    bernoulli_ns += o.bernoulli_ns; guide_ns += o.guide_ns; guide_clock_ns += o.guide_clock_ns; chain_unknown_type += o.chain_unknown_type;
    walk_steps += o.walk_steps; walk_reprojections += o.walk_reprojections; walk_off_surface += o.walk_off_surface; chain_steps += o.chain_steps;
    for (size_t i = 0; i < walk_failures.size(); ++i) walk_failures[i] += o.walk_failures[i];
    chain_m2 += o.chain_m2;
    pt_shared_m2 += o.pt_shared_m2;
    for (size_t h = 0; h < limit_m2.size(); ++h) {
      limit_m2[h] += o.limit_m2[h];
      limit_steps[h] += o.limit_steps[h];
      limit_pt_m2[h] += o.limit_pt_m2[h];
      limit_pt_steps[h] += o.limit_pt_steps[h];
      limit_censored[h] += o.limit_censored[h];
    }
    guided_trials += o.guided_trials;
    trials_tau_cut += o.trials_tau_cut;
    chain_inactive += o.chain_inactive;
    chain_skipped += o.chain_skipped;
    chain_handed += o.chain_handed;
    chain_deep += o.chain_deep;
    chain_lt_skipped += o.chain_lt_skipped;
    lt_pt_dropped += o.lt_pt_dropped;
    glint_seeds += o.glint_seeds; glint_walks += o.glint_walks; glint_found += o.glint_found;
    glint_trials += o.glint_trials; glint_rejected += o.glint_rejected; glint_pt_dropped += o.glint_pt_dropped;
    glint_capped += o.glint_capped;
    lt_photons += o.lt_photons; lt_rays += o.lt_rays; lt_splats += o.lt_splats; lt_rejected += o.lt_rejected;
    lt_chain_tries += o.lt_chain_tries; lt_chain_splats += o.lt_chain_splats;
    guided_traces += o.guided_traces;
    guided_traces_defensive += o.guided_traces_defensive;
    trace_rays += o.trace_rays;
    trace_lobes += o.trace_lobes;
    trace_pt_lobes += o.trace_pt_lobes;
    guided_trace_hits += o.guided_trace_hits;
    subpaths.insert(subpaths.end(), o.subpaths.begin(), o.subpaths.end());
    if (o.max_chain_value > max_chain_value) {
      max_chain_value = o.max_chain_value; max_chain_K = o.max_chain_K; max_chain_G = o.max_chain_G;
      max_chain_pn = o.max_chain_pn; max_chain_n = o.max_chain_n; max_chain_guided = o.max_chain_guided;
      max_chain_rate = o.max_chain_rate;
    }
  }
  std::map<std::string, double> to_map() const {
    std::map<std::string, double> m = {{"samples", double(samples)},           {"camera_rays", double(camera_rays)},
            {"rays", double(rays)},                 {"shadow_rays", double(shadow_rays)},
            {"rejected_nan", double(rejected_nan)}, {"rejected_inf", double(rejected_inf)},
            {"rejected_negative", double(rejected_negative)},
            {"depth_capped", double(depth_capped)}, {"path_vertices", double(path_vertices)},
            {"delta_prefix_rays", double(delta_prefix_rays)}, {"delta_split_paths", double(delta_split_paths)},
            {"delta_branches", double(delta_branches)},
            {"pixel_split_samples", double(pixel_split_samples)},
            {"chain_estimates", double(chain_estimates)}, {"chain_converged", double(chain_converged)},
            {"chain_contributions", double(chain_contributions)},
            {"bernoulli_trials", double(bernoulli_trials)}, {"bernoulli_capped", double(bernoulli_capped)},
            {"owned_dropped", double(owned_dropped)}, {"owned_shared", double(owned_shared)}, {"chain_ns", double(chain_ns)},
            {"bernoulli_ns", double(bernoulli_ns)}, {"guide_ns", double(guide_ns > guide_clock_ns ? guide_ns - guide_clock_ns : 0)},
            {"guide_ns_raw", double(guide_ns)}, {"guide_clock_ns", double(guide_clock_ns)},
            {"walk_steps", double(walk_steps)}, {"walk_reprojections", double(walk_reprojections)}, {"walk_off_surface", double(walk_off_surface)},
            {"chain_steps", double(chain_steps)},
            {"guided_trials", double(guided_trials)}, {"trials_tau_cut", double(trials_tau_cut)},
            {"chain_inactive", double(chain_inactive)}, {"chain_unknown_type", double(chain_unknown_type)},
            {"chain_skipped", double(chain_skipped)},
            {"chain_handed", double(chain_handed)}, {"chain_deep", double(chain_deep)},
            {"chain_lt_skipped", double(chain_lt_skipped)},
            {"lt_pt_dropped", double(lt_pt_dropped)},
            {"glint_seeds", double(glint_seeds)}, {"glint_walks", double(glint_walks)},
            {"glint_found", double(glint_found)}, {"glint_trials", double(glint_trials)},
            {"glint_rejected", double(glint_rejected)}, {"glint_pt_dropped", double(glint_pt_dropped)},
            {"glint_capped", double(glint_capped)},
            {"lt_photons", double(lt_photons)}, {"lt_rays", double(lt_rays)},
            {"lt_splats", double(lt_splats)}, {"lt_rejected", double(lt_rejected)},
            {"lt_chain_tries", double(lt_chain_tries)}, {"lt_chain_splats", double(lt_chain_splats)},
            {"guided_traces", double(guided_traces)},
            {"guided_traces_defensive", double(guided_traces_defensive)},
            {"guided_trace_hits", double(guided_trace_hits)},
            {"subpath_samples", double(subpaths.size())},
            {"max_chain_value", max_chain_value}, {"max_chain_K", max_chain_K},
            {"max_chain_G", max_chain_G}, {"max_chain_pn", max_chain_pn},
            {"max_chain_n", max_chain_n}, {"max_chain_guided", max_chain_guided},
            {"max_chain_rate", max_chain_rate}, {"chain_m2", chain_m2}, {"pt_shared_m2", pt_shared_m2}};
    for (size_t h = 0; h < limit_m2.size(); ++h) {
      const std::string slot = h == size_t(kFullSearch) ? "full" : std::to_string(h);
      m["limit_m2_" + slot] = limit_m2[h];
      m["limit_steps_" + slot] = limit_steps[h];
      m["limit_pt_m2_" + slot] = limit_pt_m2[h];
      m["limit_pt_steps_" + slot] = limit_pt_steps[h];
      m["limit_censored_" + slot] = double(limit_censored[h]);
    }
    return m;
  }
};

}  // namespace mpg
