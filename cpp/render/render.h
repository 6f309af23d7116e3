// One render pass over the (cropped) film with a tile scheduler on our own
// threads. Each sample's random stream is keyed by (seed, pass, pixel, sample),
// so the image does not depend on the number of threads.
#pragma once

#include <atomic>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "integrators/integrator.h"
#include "integrators/light_trace.h"
#include "render/stats.h"
#include "scene/scene.h"

namespace mpg {

struct PassResult {
  int width = 0, height = 0, spp = 0;
  std::vector<double> sum, sum_sq;  // height x width x 3: sums of sample values and squares
  // With PassConfig::record_costs, per pixel (height x width): the sum over its
  // samples of the chain second moment (Stats::pixel_chain_m2), the work of its
  // chain estimates (Stats::chain_steps), all its walk work (Stats::walk_steps:
  // the path tracer's MIS rounds too) and its rays (camera, extension, shadow). Counts, not times: the rates learned from them, and so the
  // image, are the same on every run. alt_sum / alt_sum_sq (height x width x 3):
  // the sums of the samples' "path tracer alone" values and their squares
  // (Stats::sample_alt_delta), for the rate-0 decision; alt_hits (height x
  // width): the samples in which the path tracer found owned chain light.
  // delta_rays (height x width): the rays its samples traced after delta
  // scattering only (Stats::delta_prefix_rays), what an extra camera path of
  // the delta split costs besides its camera ray.
  // delta_sum / delta_sum_sq (height x width x 3): the sums of the samples'
  // light seen through delta scattering only (Stats::sample_delta_L) and of
  // its squares, for the variance the delta split divides.
  std::vector<double> chain_m2, chain_steps, walk_steps, rays, alt_sum, alt_sum_sq, alt_hits, delta_rays;
  // With PassConfig::record_classes (height x width x Stats::kClasses): per
  // pixel the sums over its samples of each class's part of the sample value
  // (mean over RGB; Stats::Class) and of its squares
  std::vector<double> class_sum, class_sum_sq;
  // ... trace_sum[i] / trace_sum_sq[i] (height x width x 3): the same samples'
  // values at rate 0 with k = 2^i guided traces formed from two recorded ones
  // (Stats::record_trace; the path tracer alone's values where none ran), trace_var[i] (height
  // x width): the sums of one scaled trace's variance (Z_1 - Z_2)^2 / 2 (mean
  // over RGB); trace_n: the samples that recorded them (one in
  // Stats::kTraceRecordEvery), the sums being over those; trace_hits: of those,
  // the samples in which the path tracer or a trace found chain light;
  // trace_rays: the two traces' rays (left out of `rays`); trace_lobes /
  // trace_pt_lobes: the lobes their densities and the path tracer's weights
  // against them visited (Stats::trace_lobes)
  std::vector<double> trace_sum[Stats::kTraceKs], trace_sum_sq[Stats::kTraceKs], trace_var[Stats::kTraceKs];
  std::vector<double> trace_n, trace_hits, trace_rays, trace_lobes, trace_pt_lobes;
  // ... trace_tail[i] (height x width, i = 0: the path tracer alone, i + 1:
  // 2^i traces) and trace_chain_sum (height x width x 3): the same samples'
  // sums of Stats::sample_tail and sample_chain_part
  // trace_seen[i]: the records' own estimate of the same second moments,
  // P^2 + (Z_1^2 + Z_2^2) / (2 k), P the path tracer's chain paths as
  // weighted for k traces (unbiased as well where a sample has at most one
  // chain path; the tails' rare paths as often as the records see them)
  std::vector<double> trace_tail[Stats::kTraceKs + 1], trace_seen[Stats::kTraceKs + 1], trace_chain_sum;
  std::vector<double> delta_sum, delta_sum_sq;
  // ... and, where the integrator branches (Integrator::delta_branched), one
  // sample in Stats::kBranchRecordEvery whose own path traced on after a delta
  // vertex (it saw glass or a mirror) also records two branched delta paths
  // (B_1, B_2) and two plain ones (U_1, U_2) of one camera ray of its own (an
  // independent film position), after the sample, whose value they do not
  // touch: bdelta_n (height x width) the samples that did, bdelta_rays their
  // rays (left out of `rays`), bdelta_within / udelta_within the sums of (B_1 -
  // B_2)^2 / 2 and (U_1 - U_2)^2 / 2 (mean over RGB): each kind's variance
  // at a fixed film position, which the delta split's Sobol positions do not
  // take away (chain_rates.learn_delta_split: where the trees keep much of
  // it, plain paths).
  std::vector<double> bdelta_n, bdelta_rays, bdelta_within, udelta_within;
  // With record_delta alone (the render's passes): per pixel the sums
  // (height x width x 3) of the delta split's extra paths' values
  // (Integrator::Li_delta, branched or plain as the pixel ran them) and of
  // their squares, and the count of such paths and their rays, camera rays
  // included (height x width): one extra path's variance and cost, by which
  // mpg's held-out check sets a split pixel's count
  // (chain_rates.DeltaSplitRefiner.measured_counts).
  std::vector<double> split_path_sum, split_path_sum_sq, split_path_n, split_path_rays;
  // The light tracer's photons of this pass (Integrator::light_tracer; 0:
  // none) and per pixel (height x width x 3) the sums of their splats and of
  // the splats' squares: the pixel's light-traced part is lt_sum / photons
  // over all passes, and each photon is one independent sample of it.
  uint64_t lt_photons = 0;
  std::vector<double> lt_sum, lt_sum_sq;
  // ... and their work: the rays they traced (their paths and the splats'
  // visibility) and their manifold-walk steps (camera-side chains); mpg's
  // photon rate model (chain_rates.learn_photon_rate), which counts work
  // rather than timing it
  uint64_t lt_work_rays = 0, lt_work_walk_steps = 0;
  Stats stats;
  double seconds = 0.0;
  bool cancelled = false;
};

struct PassConfig {
  int spp = 1;
  uint64_t seed = 0;
  uint64_t pass = 0;
  int threads = 0;   // 0: all hardware threads
  int tile = 16;
  // Per-pixel chain rate (crop height x width, each 0 or in [0.001, 1]), or
  // null. 0: the path tracer takes the chains' light whole in that pixel.
  std::shared_ptr<const std::vector<float>> chain_rate_map;
  // Per-pixel delta-split count k >= 1 (crop height x width, integers), or
  // null (1 everywhere): each sample's light seen through delta scattering
  // only is averaged with k - 1 extra camera paths of that light alone.
  std::shared_ptr<const std::vector<float>> delta_split_map;
  // Per pixel whether the delta split's extra paths branch (crop height x
  // width, 1 or 0), or null (1 everywhere): 0 takes the plain Only path in a
  // branching integrator's pixel (and keeps the sample's own delta part in
  // the mean, as an integrator that does not branch). mpg learns it with the
  // split (chain_rates.learn_delta_split).
  std::shared_ptr<const std::vector<float>> delta_branch_map;
  // Per-pixel sample split k >= 1 (crop height x width, integers), or null (1
  // everywhere): each sample of the pixel is the mean of k independent camera
  // samples (camera ray, Li, delta split), so its variance is 1/k of one.
  std::shared_ptr<const std::vector<float>> pixel_split_map;
  // Per-pixel count of guided traces in pixels of rate 0 (crop height x
  // width, integers 0..64; ChainParams::handoff_guided's k per pixel; 0: off),
  // or null (the integrator's handoff_guided everywhere). In training passes
  // (record_costs) 0 also switches off the record of the trace's forms.
  std::shared_ptr<const std::vector<float>> guided_trace_map;
  // Per-pixel chain rate at the separators after a path's first in pixels of
  // rate 0 (crop height x width, each 0 or in [0.001, 1]; 0: the path tracer
  // there too), or null (the integrator's handoff_deep everywhere). mpg's
  // handoff_all gives the pixels it hands off their learned rate there.
  std::shared_ptr<const std::vector<float>> deep_rate_map;
  bool record_costs = false;
  // Per pixel the sums and squares of each sample's light seen through delta
  // scattering only (PassResult::delta_sum / delta_sum_sq, one camera path's
  // own part a sample) without the rest of record_costs: the render's passes
  // for mpg's held-out check of its delta split (chain_rates.DeltaSplitRefiner).
  // record_costs records them too.
  bool record_delta = false;
  // ... and, with record_costs and a branching integrator, the records of the
  // branched and plain delta paths (PassResult::bdelta_*; mpg's delta_plain)
  bool record_branch = false;
  // Per pixel the sums and squares (mean over RGB) of each sample's value
  // split by where it entered (Stats::kClasses; PassResult::class_sum)
  bool record_classes = false;
  // Trace the integrator's light-tracer photons (Integrator::light_tracer);
  // off in mpg's training passes, which never reach the image
  bool light_trace = true;
  // Pixel positions from a per-pixel randomly shifted Sobol (0,2)-sequence
  // (core/rng.h shifted_sobol_2d) instead of independent random numbers; the
  // scene's sampler stratified/multijitter/ldsampler/... asks for it. Point
  // (sample_offset + k) x pixel_split + sub of the pixel's sequence is the
  // position of sample k's sub-sample sub, so consecutive passes continue one
  // sequence when sample_offset counts the samples of the passes before.
  bool stratify = false;
  uint64_t sample_offset = 0;
  // Salts the per-pixel shifts of the Sobol sequences (the positions' and the
  // delta split's): 0 keeps the seed's own; a caller that changes a map from
  // the samples of earlier passes (mpg.render's pixel_split_refine) starts a
  // new epoch there, with sample_offset counted from its start, so no later
  // position is a function of a shift the earlier samples depended on.
  uint64_t sequence_epoch = 0;
  // Photon blocks (RenderJob::kLtBlock photons each) per wave: the first
  // wave runs in the tiles' threads, any later one after them; a wave's
  // splats are held at once (at most one per photon, 16 bytes: 64 MiB at
  // 1024). A test sets it low to run several waves.
  int lt_wave_blocks = 1024;
};

class RenderJob {
 public:
  RenderJob(std::shared_ptr<const Scene> scene, std::shared_ptr<const Integrator> integrator,
            PassConfig cfg);
  ~RenderJob();
  void start();
  bool wait_for(double seconds);  // true when finished
  void cancel() { cancel_.store(true); }
  double progress() const;        // fraction of tiles done
  PassResult& result() { return result_; }

 private:
  void run();
  void lt_begin();
  void lt_block(int wave, int j, Stats& st);
  void lt_add(int nb);
  void lt_blocks(std::atomic<int>& next, int wave, int nb, Stats& st, uint64_t& rays, uint64_t& steps);
  void light_trace(std::vector<Stats>& stats, int nthreads, int first_wave, std::vector<uint64_t>& rays,
                   std::vector<uint64_t>& steps);
  static constexpr uint64_t kLtBlock = 4096;
  std::shared_ptr<const Scene> scene_;
  std::shared_ptr<const Integrator> integrator_;
  PassConfig cfg_;
  PassResult result_;
  std::atomic<bool> cancel_{false}, done_{false};
  // wait_for sleeps on this until run() sets done_ (a 5 ms polling sleep lost
  // 2.5 ms a pass on average: 50 ms of a 2 s render's 20 passes)
  std::mutex done_mutex_;
  std::condition_variable done_cv_;
  std::atomic<int> tiles_done_{0}, lt_blocks_done_{0};
  int tiles_total_ = 1;
  uint64_t lt_photons_ = 0;   // this pass's photons (light tracer)
  int lt_blocks_ = 0;
  std::vector<std::vector<LightSplat>> lt_out_;   // a wave's splats, per block
  std::thread thread_;
};

// Synchronous convenience (tests, benchmarks).
PassResult render_pass(std::shared_ptr<const Scene> scene, std::shared_ptr<const Integrator> integrator,
                       const PassConfig& cfg);

}  // namespace mpg
