#include "render/render.h"

#include <xmmintrin.h>
#include <pmmintrin.h>

#include <algorithm>
#include <chrono>
#include <stdexcept>

#include "core/rng.h"
#include "integrators/light_trace.h"

namespace mpg {

RenderJob::RenderJob(std::shared_ptr<const Scene> scene, std::shared_ptr<const Integrator> integrator,
                     PassConfig cfg)
    : scene_(std::move(scene)), integrator_(std::move(integrator)), cfg_(cfg) {
  const Camera& c = scene_->camera;
  const int tx = (c.crop_w + cfg_.tile - 1) / cfg_.tile, ty = (c.crop_h + cfg_.tile - 1) / cfg_.tile;
  tiles_total_ = std::max(1, tx * ty);
  if (cfg_.lt_wave_blocks < 1) throw std::invalid_argument("lt_wave_blocks must be >= 1");
  // Training passes never reach the image: no photons there (record_costs,
  // or cfg_.light_trace off by mpg's training loop).
  const LightTracer* lt = integrator_->light_tracer();
  if (lt && &lt->scene() != scene_.get())
    throw std::invalid_argument("the integrator's light tracer was made for another scene");
  if (lt && cfg_.light_trace && !cfg_.record_costs) {
    const double n = double(lt->photons_per_sample()) * double(cfg_.spp) * double(c.crop_w) * double(c.crop_h);
    lt_photons_ = uint64_t(std::llround(std::max(1.0, n)));
    lt_blocks_ = int((lt_photons_ + kLtBlock - 1) / kLtBlock);
  }
}

RenderJob::~RenderJob() {
  cancel_.store(true);
  if (thread_.joinable()) thread_.join();
}

void RenderJob::start() { thread_ = std::thread([this] { run(); }); }

bool RenderJob::wait_for(double seconds) {
  {
    std::unique_lock<std::mutex> lock(done_mutex_);
    // (clamped: a duration past ~1e10 s overflows the clock's nanoseconds)
    if (!done_cv_.wait_for(lock, std::chrono::duration<double>(std::clamp(seconds, 0.0, 1e6)),
                           [this] { return done_.load(); }))
      return false;
  }
  if (thread_.joinable()) thread_.join();
  return true;
}

double RenderJob::progress() const {
  // (a photon block counted as a tile: both are a small share of a pass)
  return double(tiles_done_.load() + lt_blocks_done_.load()) / double(tiles_total_ + lt_blocks_);
}

void RenderJob::run() {
  const auto t0 = std::chrono::steady_clock::now();
  const Scene& scene = *scene_;
  const Camera& cam = scene.camera;
  const int W = cam.crop_w, H = cam.crop_h, T = cfg_.tile;
  const int tx = (W + T - 1) / T;
  result_.width = W;
  result_.height = H;
  result_.spp = cfg_.spp;
  result_.sum.assign(size_t(W) * H * 3, 0.0);
  result_.sum_sq.assign(size_t(W) * H * 3, 0.0);
  const bool costs = cfg_.record_costs;
  const bool classes = cfg_.record_classes;
  const bool delta_rec = costs || cfg_.record_delta;
  constexpr int NC = Stats::kClasses;
  const bool split_rec = cfg_.record_delta && !costs;   // (PassResult::split_path_*)
  if (split_rec) {
    result_.delta_sum.assign(size_t(W) * H * 3, 0.0);
    result_.delta_sum_sq.assign(size_t(W) * H * 3, 0.0);
    result_.split_path_sum.assign(size_t(W) * H * 3, 0.0);
    result_.split_path_sum_sq.assign(size_t(W) * H * 3, 0.0);
    result_.split_path_n.assign(size_t(W) * H, 0.0);
    result_.split_path_rays.assign(size_t(W) * H, 0.0);
  }
  if (classes) {
    result_.class_sum.assign(size_t(W) * H * NC, 0.0);
    result_.class_sum_sq.assign(size_t(W) * H * NC, 0.0);
  }
  if (costs) {
    result_.chain_m2.assign(size_t(W) * H, 0.0);
    result_.chain_steps.assign(size_t(W) * H, 0.0);
    result_.walk_steps.assign(size_t(W) * H, 0.0);
    result_.rays.assign(size_t(W) * H, 0.0);
    result_.alt_sum.assign(size_t(W) * H * 3, 0.0);
    result_.alt_hits.assign(size_t(W) * H, 0.0);
    result_.alt_sum_sq.assign(size_t(W) * H * 3, 0.0);
    for (int f = 0; f < Stats::kTraceKs; ++f) {
      result_.trace_sum[f].assign(size_t(W) * H * 3, 0.0);
      result_.trace_sum_sq[f].assign(size_t(W) * H * 3, 0.0);
      result_.trace_var[f].assign(size_t(W) * H, 0.0);
    }
    for (auto& t : result_.trace_tail) t.assign(size_t(W) * H, 0.0);
    for (auto& t : result_.trace_seen) t.assign(size_t(W) * H, 0.0);
    result_.trace_chain_sum.assign(size_t(W) * H * 3, 0.0);
    result_.trace_hits.assign(size_t(W) * H, 0.0);
    result_.trace_n.assign(size_t(W) * H, 0.0);
    result_.trace_rays.assign(size_t(W) * H, 0.0);
    result_.trace_lobes.assign(size_t(W) * H, 0.0);
    result_.trace_pt_lobes.assign(size_t(W) * H, 0.0);
    result_.delta_rays.assign(size_t(W) * H, 0.0);
    result_.delta_sum.assign(size_t(W) * H * 3, 0.0);
    result_.delta_sum_sq.assign(size_t(W) * H * 3, 0.0);
    result_.bdelta_n.assign(size_t(W) * H, 0.0);
    result_.bdelta_rays.assign(size_t(W) * H, 0.0);
    result_.bdelta_within.assign(size_t(W) * H, 0.0);
    result_.udelta_within.assign(size_t(W) * H, 0.0);
  }
  const std::vector<float>* qmap = cfg_.chain_rate_map.get();
  if (qmap && qmap->size() != size_t(W) * H) qmap = nullptr;  // checked by the bindings
  const std::vector<float>* gmap = cfg_.guided_trace_map.get();
  if (gmap && gmap->size() != size_t(W) * H) gmap = nullptr;
  const std::vector<float>* dmap = cfg_.deep_rate_map.get();
  if (dmap && dmap->size() != size_t(W) * H) dmap = nullptr;
  const std::vector<float>* kmap = cfg_.delta_split_map.get();
  if (kmap && kmap->size() != size_t(W) * H) kmap = nullptr;
  const std::vector<float>* smap = cfg_.pixel_split_map.get();
  const bool branched = integrator_->delta_branched();  // (Li_delta's kind, once per pass)
  const std::vector<float>* bmap = cfg_.delta_branch_map.get();
  if (bmap && bmap->size() != size_t(W) * H) bmap = nullptr;
  const bool split_sobol = integrator_->delta_split_sobol();
  if (smap && smap->size() != size_t(W) * H) smap = nullptr;
  int nthreads = cfg_.threads > 0 ? cfg_.threads : int(std::thread::hardware_concurrency());
  nthreads = std::max(1, std::min(nthreads, tiles_total_));
  std::atomic<int> next_tile{0};
  std::vector<Stats> stats(static_cast<size_t>(nthreads));

  auto tiles = [&](int tid) {
    Stats& st = stats[size_t(tid)];
    st.cancel = &cancel_;
    // A camera ray through film pixel (fx, fy), its position drawn from the pixel filter.
    // With cfg_.stratify and an index >= 0 the position is point `index` of the
    // pixel's Sobol sequence shifted by `shift` (the pixel's two 32-bit words).
    // (PassConfig::sequence_epoch: 0 salts nothing)
    const uint64_t epoch_salt = cfg_.sequence_epoch ? mix64(cfg_.sequence_epoch * 0x9E3779B97F4A7C15ULL) : 0;
    const uint64_t shift_key = mix64(cfg_.seed ^ 0x5851f42d4c957f2dULL ^ epoch_salt);
    // the delta split's own sequence per pixel (its shift apart from the positions')
    const uint64_t split_key = mix64(cfg_.seed ^ 0x2545f4914f6cdd1dULL ^ epoch_salt);
    // (sobol: the sequence's point even in an unstratified pass: the delta
    // split's extra paths, Integrator::delta_split_sobol)
    auto camera_ray = [&](PCG32& rng, int fx, int fy, Vec3& o, Vec3& d, float& tmin, float& tmax,
                          int64_t index = -1, uint64_t shift = 0, bool sobol = false) {
      float u0, u1;
      if ((cfg_.stratify || sobol) && index >= 0) {
        shifted_sobol_2d(uint32_t(uint64_t(index)), uint32_t(shift), uint32_t(shift >> 32), u0, u1);
      } else {
        u0 = rng.next_float();
        u1 = rng.next_float();
      }
      const float ox = cam.filter.sample(u0);
      const float oy = cam.filter.sample(u1);
      cam.generate_ray(Vec2(float(fx) + 0.5f + ox, float(fy) + 0.5f + oy), o, d, tmin, tmax);
      st.camera_rays++;
    };
    for (;;) {
      if (cancel_.load(std::memory_order_relaxed)) return;
      const int tile = next_tile.fetch_add(1);
      if (tile >= tiles_total_) return;
      const int x0 = (tile % tx) * T, y0 = (tile / tx) * T;
      const int x1 = std::min(x0 + T, W), y1 = std::min(y0 + T, H);
      for (int y = y0; y < y1; ++y) {
        for (int x = x0; x < x1; ++x) {
          const int fx = cam.crop_x + x, fy = cam.crop_y + y;
          const uint64_t pixel = uint64_t(fy) * uint64_t(cam.width) + uint64_t(fx);
          const uint64_t shift = mix64(shift_key ^ pixel);  // from the seed, epoch and pixel only
          const uint64_t split_shift = split_sobol ? mix64(split_key ^ pixel) : 0;
          double s[3] = {0, 0, 0}, s2[3] = {0, 0, 0}, a[3] = {0, 0, 0}, a2[3] = {0, 0, 0}, hits = 0;
          double ds[3] = {0, 0, 0}, ds2[3] = {0, 0, 0};
          double ps[3] = {0, 0, 0}, ps2[3] = {0, 0, 0}, pn = 0, prays = 0;   // (split_rec)
          double cs[NC] = {}, cs2[NC] = {};   // (record_classes)
          st.record_classes = classes;
          double ts[Stats::kTraceKs][3] = {}, ts2[Stats::kTraceKs][3] = {}, tvar[Stats::kTraceKs] = {}, thits = 0;
          double tn = 0;   // samples that recorded the traces
          double ttail[Stats::kTraceKs + 1] = {}, tseen[Stats::kTraceKs + 1] = {}, tchain[3] = {};
          st.film_x = fx;
          st.film_y = fy;
          st.pixel_chain_rate = qmap ? (*qmap)[size_t(y) * W + x] : -1.f;
          st.pixel_trace_k = gmap ? int((*gmap)[size_t(y) * W + x]) : -1;
          st.pixel_deep_rate = dmap ? (*dmap)[size_t(y) * W + x] : -1.f;
          st.pixel_chain_m2 = 0.0;
          const int ksplit = kmap ? std::max(1, int((*kmap)[size_t(y) * W + x])) : 1;
          st.split_delta = ksplit > 1;
          // the split's extra paths branched here (the integrator's kind, unless the map says no)
          const bool pbranch = branched && !(bmap && !((*bmap)[size_t(y) * W + x] > 0.f));
          double bn = 0, brays = 0, bw = 0, uw = 0;   // (record_costs, branched: PassResult::bdelta_*)
          const int kpix = smap ? std::max(1, int((*smap)[size_t(y) * W + x])) : 1;
          const uint64_t steps0 = st.chain_steps, walk0 = st.walk_steps, rays0 = st.rays + st.shadow_rays + st.camera_rays;
          const uint64_t delta0 = st.delta_prefix_rays, trace0 = st.trace_rays;
          const uint64_t lobes0 = st.trace_lobes, pt_lobes0 = st.trace_pt_lobes;
          for (int k = 0; k < cfg_.spp; ++k) {
            // A cancelled pass is dropped whole (never splatted), so stopping
            // mid-tile is safe; checking per sample bounds the overshoot of a
            // time limit by one sample, not one tile (a tile of chain
            // estimates took seconds).
            if (cancel_.load(std::memory_order_relaxed)) return;
            PCG32 rng = make_stream(cfg_.seed, cfg_.pass, pixel, uint64_t(k));
            const uint64_t delta_k0 = st.delta_prefix_rays;   // (the branch records: did this sample see glass?)
            // the guided trace's record in one sample of kTraceRecordEvery (its
            // traces, and the path tracer's weights against them, cost about
            // as much as the sample: in every sample they took a training
            // iteration's worth of time); which one moves along the pixels
            // and, as the branch records' below, with the pass (a training's
            // 1-spp passes, its first iteration's and a continuation's, had
            // all recorded at the same pixels)
            st.record_trace = costs && (pixel + uint64_t(k) + cfg_.pass) % uint64_t(Stats::kTraceRecordEvery) == 0;
            // The pixel split: the sample is the mean of kpix camera samples
            // drawn one after the other from the sample's own random stream
            // (kpix = 1: the plain sample, bit for bit).
            Color L(0.f);
            Color cls[NC] = {};   // (record_classes) the sample's value by class
            for (int sub = 0; sub < kpix; ++sub) {
              Vec3 o, d;
              float tmin, tmax;
              camera_ray(rng, fx, fy, o, d, tmin, tmax,
                         int64_t((cfg_.sample_offset + uint64_t(k)) * uint64_t(kpix) + uint64_t(sub)), shift);
              st.sample_alt_delta = Color(0.f);
              st.sample_owned_hit = false;
              for (Color& c : st.sample_trace_hits_delta) c = Color(0.f);
              for (TraceSample& t : st.sample_traces) t = TraceSample{};
              st.sample_trace_hit = false;
              st.sample_trace_recorded = false;
              for (double& t : st.sample_tail) t = 0.0;
              st.sample_chain_part = Color(0.f);
              for (Color& c : st.sample_seen_P) c = Color(0.f);
              st.sample_delta_L = Color(0.f);
              if (classes)
                for (Color& c : st.sample_class) c = Color(0.f);
              Color Ls = integrator_->Li(scene, o, d, tmin, tmax, rng, st);
              if (classes) {
                for (int c = 0; c < NC; ++c) cls[c] += st.sample_class[c];
                // the light seen through delta scattering only: the path's own,
                // or the split's mean below
                if (ksplit <= 1) cls[Stats::kClassDelta] += st.sample_delta_L;
                cls[Stats::kClassGlints] += st.sample_glint;
              }
              if (ksplit > 1) {
                // The light seen through delta scattering only, left out of Ls:
                // the mean of this path's and k - 1 more camera paths' (each an
                // unbiased estimate of it, the same pixel filter, the sample's own
                // random stream).
                // Branched extra paths (delta_branched) are far less noisy than
                // this path's own delta part: the mean of the k - 1 of them alone.
                Color D = pbranch ? Color(0.f) : st.sample_delta_L;
                for (int j = 1; j < ksplit; ++j) {
                  Vec3 o2, d2;
                  float tmin2, tmax2;
                  const uint64_t prays0 = st.rays + st.shadow_rays + st.camera_rays;
                  // With delta_split_sobol the extra paths' film positions are
                  // the points of one randomly shifted Sobol (0,2)-sequence per
                  // pixel, continued over the samples and passes (point
                  // ((offset + k) kpix + sub)(ksplit - 1) + j - 1): each is uniform
                  // in the pixel, so each extra path stays unbiased, and a
                  // branched path's value is nearly a function of its position
                  // alone, which the net then stratifies (the thin bright
                  // slivers of the light seen in the glass). Else independent.
                  if (split_sobol)
                    camera_ray(rng, fx, fy, o2, d2, tmin2, tmax2,
                               int64_t(((cfg_.sample_offset + uint64_t(k)) * uint64_t(kpix) + uint64_t(sub)) *
                                           uint64_t(ksplit - 1) + uint64_t(j - 1)),
                               split_shift, true);
                  else
                    camera_ray(rng, fx, fy, o2, d2, tmin2, tmax2);
                  st.delta_split_paths++;
                  const Color Dj = integrator_->Li_delta(scene, o2, d2, tmin2, tmax2, rng, st, pbranch);
                  D += Dj;
                  if (split_rec) {
                    prays += double(st.rays + st.shadow_rays + st.camera_rays - prays0);
                    if (is_finite(Dj)) {
                      for (int c = 0; c < 3; ++c) {
                        ps[c] += Dj[c];
                        ps2[c] += double(Dj[c]) * Dj[c];
                      }
                      pn += 1.0;
                    }
                  }
                }
                Ls += D * (1.f / float(pbranch ? ksplit - 1 : ksplit));
                if (classes) cls[Stats::kClassDelta] += D * (1.f / float(pbranch ? ksplit - 1 : ksplit));
              }
              L += Ls;
              if (sub > 0) st.pixel_split_samples++;
            }
            if (kpix > 1) L *= 1.f / float(kpix);
            st.samples++;
            const bool finite = std::isfinite(L.x) && std::isfinite(L.y) && std::isfinite(L.z);
            const bool ok = finite && L.x >= 0.f && L.y >= 0.f && L.z >= 0.f;
            if (!finite) {
              if (std::isnan(L.x) || std::isnan(L.y) || std::isnan(L.z)) st.rejected_nan++;
              else st.rejected_inf++;
              L = Color(0.f);
            } else if (L.x < 0.f || L.y < 0.f || L.z < 0.f) {
              st.rejected_negative++;
              L = Color(0.f);
            }
            for (int c = 0; c < 3; ++c) {
              s[c] += L[c];
              s2[c] += double(L[c]) * L[c];
            }
            if (classes && ok) {
              // the rest: what no class above holds (NEE, emitters seen after
              // a separator without chains, ...); a rejected sample counts 0
              Color rest = L;
              for (int c = 0; c < NC; ++c) {
                if (c != Stats::kClassOther) {
                  cls[c] *= 1.f / float(kpix);
                  rest -= cls[c];
                }
              }
              cls[Stats::kClassOther] = rest;
              for (int c = 0; c < NC; ++c) {
                const double v = (double(cls[c].x) + cls[c].y + cls[c].z) / 3.0;
                if (std::isfinite(v)) {
                  cs[c] += v;
                  cs2[c] += v * v;
                }
              }
            }
            if (delta_rec) {
              // the sample's own camera path's light seen through delta
              // scattering only (the last sub-sample's in a split pixel: one
              // path's, whatever the splits)
              const Color Dl = st.sample_delta_L;
              if (ok && std::isfinite(Dl.x) && std::isfinite(Dl.y) && std::isfinite(Dl.z))
                for (int c = 0; c < 3; ++c) {
                  ds[c] += Dl[c];
                  ds2[c] += double(Dl[c]) * Dl[c];
                }
            }
            if (costs) {
              // The path tracer alone; a rejected sample (L = 0) counts 0 here too.
              const Color A = ok ? L + st.sample_alt_delta : Color(0.f);
              if (ok && st.sample_owned_hit) hits += 1.0;
              if (std::isfinite(A.x) && std::isfinite(A.y) && std::isfinite(A.z))
                for (int c = 0; c < 3; ++c) {
                  const double v = std::max(double(A[c]), 0.0);
                  a[c] += v;
                  a2[c] += v * v;
                }
              // ... and with k = 2^i guided traces (Stats::record_trace): the
              // value with the two recorded traces in place of k, Z_j = k f_j /
              // (b_j + k g_j), Y = A + (w_k - 1) hits + (Z_1 + Z_2) / 2, and one
              // trace's variance (Z_1 - Z_2)^2 / 2 (mean over RGB): k traces'
              // value has E[(T - I)^2] = E[(Y - I)^2] + (1/k - 1/2) Var(Z)
              // (mpg.chain_rates.learn_rates_traced)
              // (a pass without a guide, or a pixel at rate 0, records none: not counted)
              static_assert(Stats::kTraceRecorded == 2, "the values below are formed from two traces");
              const bool rec = st.record_trace && st.sample_trace_recorded;
              if (rec) tn += 1.0;
              // each recorded trace's share scaled to the whole, Z = k f / (b + k g), per k
              Color z[Stats::kTraceKs][Stats::kTraceRecorded];
              for (int f = 0; f < Stats::kTraceKs && rec; ++f)
                for (int j = 0; j < Stats::kTraceRecorded; ++j)
                  z[f][j] = st.sample_traces[j].weighted(1 << f) * float(1 << f);
              if (rec && ok) {
                const Color& Cp = st.sample_chain_part;
                bool fin = std::isfinite(Cp.x) && std::isfinite(Cp.y) && std::isfinite(Cp.z);
                for (double t : st.sample_tail) fin = fin && std::isfinite(t);
                for (const Color& P : st.sample_seen_P) fin = fin && std::isfinite(P.x) && std::isfinite(P.y) && std::isfinite(P.z);
                if (fin) {
                  for (int f = 0; f <= Stats::kTraceKs; ++f) ttail[f] += st.sample_tail[f];
                  for (int c = 0; c < 3; ++c) tchain[c] += Cp[c];
                  // the records' own: P^2 + (Z_1^2 + Z_2^2) / (2 k), mean over RGB
                  tseen[0] += mean_square(st.sample_seen_P[0]);
                  for (int f = 0; f < Stats::kTraceKs; ++f) {
                    double z2 = 0.0;
                    for (int j = 0; j < Stats::kTraceRecorded; ++j)
                      if (st.sample_traces[j].tail_ok) z2 += mean_square(z[f][j]);
                    const double v = mean_square(st.sample_seen_P[f + 1]) + z2 / (2.0 * (1 << f));
                    if (std::isfinite(v)) tseen[f + 1] += v;
                  }
                }
              }
              if (rec && ok && (st.sample_owned_hit || st.sample_trace_hit)) thits += 1.0;
              for (int f = 0; f < Stats::kTraceKs && rec; ++f) {
                const Color& z1 = z[f][0];
                const Color& z2 = z[f][1];
                const Color Tv = ok ? A + st.sample_trace_hits_delta[f] + (z1 + z2) * 0.5f : Color(0.f);
                if (!(std::isfinite(Tv.x) && std::isfinite(Tv.y) && std::isfinite(Tv.z))) continue;
                double dz = 0.0;
                for (int c = 0; c < 3; ++c) {
                  const double v = std::max(double(Tv[c]), 0.0);
                  ts[f][c] += v;
                  ts2[f][c] += v * v;
                  const double d = double(z1[c]) - double(z2[c]);
                  dz += d * d / 6.0;   // (z1 - z2)^2 / 2, mean over RGB
                }
                if (ok && std::isfinite(dz)) tvar[f] += dz;
              }
            }
            if (costs && branched && cfg_.record_branch && st.delta_prefix_rays > delta_k0 &&
                (pixel + uint64_t(k) + cfg_.pass) % uint64_t(Stats::kBranchRecordEvery) == 1) {
              // The record of two branched and two plain delta paths of one
              // camera ray at an independent film position (PassResult::bdelta_*),
              // in a sample whose own path traced on after a delta vertex:
              // their differences' squares / 2 are each kind's variance at a
              // fixed position, which the split's Sobol positions do not take
              // away. After the sample, off its value, its per-pixel records
              // and the pixel's rays (the pass's Stats counters do count them).
              // Which samples record moves with the pass.
              const uint64_t r0 = st.rays + st.shadow_rays + st.camera_rays;
              Vec3 o2, d2;
              float tmin2, tmax2;
              camera_ray(rng, fx, fy, o2, d2, tmin2, tmax2);
              const Color B = integrator_->Li_delta(scene, o2, d2, tmin2, tmax2, rng, st, true);
              const Color B2 = integrator_->Li_delta(scene, o2, d2, tmin2, tmax2, rng, st, true);
              const Color U1 = integrator_->Li_delta(scene, o2, d2, tmin2, tmax2, rng, st, false);
              const Color U2 = integrator_->Li_delta(scene, o2, d2, tmin2, tmax2, rng, st, false);
              brays += double(st.rays + st.shadow_rays + st.camera_rays - r0);
              bn += 1.0;
              if (is_finite(B) && is_finite(B2) && is_finite(U1) && is_finite(U2)) {
                for (int c = 0; c < 3; ++c) {
                  const double db = double(B[c]) - B2[c], du = double(U1[c]) - U2[c];
                  bw += db * db / 6.0;   // (B - B2)^2 / 2, mean over RGB
                  uw += du * du / 6.0;
                }
              }
            }
          }
          const size_t i = (size_t(y) * W + x) * 3;
          for (int c = 0; c < 3; ++c) {
            result_.sum[i + c] = s[c];
            result_.sum_sq[i + c] = s2[c];
          }
          if (classes) {
            const size_t j = (size_t(y) * W + x) * NC;
            for (int c = 0; c < NC; ++c) {
              result_.class_sum[j + c] = cs[c];
              result_.class_sum_sq[j + c] = cs2[c];
            }
          }
          if (costs) {
            const size_t j = size_t(y) * W + x;
            result_.chain_m2[j] = st.pixel_chain_m2;
            result_.chain_steps[j] = double(st.chain_steps - steps0);
            result_.walk_steps[j] = double(st.walk_steps - walk0);
            // (the training's guided traces apart: a cost of the rate-0 option alone)
            result_.trace_rays[j] = double(st.trace_rays - trace0);
            result_.rays[j] = double(st.rays + st.shadow_rays + st.camera_rays - rays0) - result_.trace_rays[j] - brays;
            result_.bdelta_n[j] = bn;
            result_.bdelta_rays[j] = brays;
            result_.bdelta_within[j] = bw;
            result_.udelta_within[j] = uw;
            result_.trace_hits[j] = thits;
            result_.trace_n[j] = tn;
            result_.trace_lobes[j] = double(st.trace_lobes - lobes0);
            result_.trace_pt_lobes[j] = double(st.trace_pt_lobes - pt_lobes0);
            for (int f = 0; f < Stats::kTraceKs; ++f) result_.trace_var[f][j] = tvar[f];
            for (int f = 0; f <= Stats::kTraceKs; ++f) {
              result_.trace_tail[f][j] = ttail[f];
              result_.trace_seen[f][j] = tseen[f];
            }
            for (int c = 0; c < 3; ++c) result_.trace_chain_sum[i + c] = tchain[c];
            result_.alt_hits[j] = hits;
            result_.delta_rays[j] = double(st.delta_prefix_rays - delta0);
            for (int c = 0; c < 3; ++c) {
              result_.alt_sum[i + c] = a[c];
              result_.alt_sum_sq[i + c] = a2[c];
              for (int f = 0; f < Stats::kTraceKs; ++f) {
                result_.trace_sum[f][i + c] = ts[f][c];
                result_.trace_sum_sq[f][i + c] = ts2[f][c];
              }
            }
          }
          if (delta_rec)
            for (int c = 0; c < 3; ++c) {
              result_.delta_sum[i + c] = ds[c];
              result_.delta_sum_sq[i + c] = ds2[c];
            }
          if (split_rec) {
            for (int c = 0; c < 3; ++c) {
              result_.split_path_sum[i + c] = ps[c];
              result_.split_path_sum_sq[i + c] = ps2[c];
            }
            result_.split_path_n[size_t(y) * W + x] = pn;
            result_.split_path_rays[size_t(y) * W + x] = prays;
          }
        }
      }
      tiles_done_.fetch_add(1);
    }
  };

  // The pass's photons (light_trace) follow the tiles in the same threads: each
  // thread takes photon blocks once no tile is left, so the photons fill the
  // tiles' tail instead of waiting for a second pool (a 1-spp pass of the
  // sphere spent 2 ms more on its photons than a 16-spp pass's share).
  // The first wave only; more waves (over 4 M photons a pass at the default
  // PassConfig::lt_wave_blocks) after the join.
  // (all the threads asked for, whatever the tile count)
  int nlt = cfg_.threads > 0 ? cfg_.threads : int(std::thread::hardware_concurrency());
  nlt = lt_blocks_ > 0 ? std::max(1, std::min(nlt, lt_blocks_)) : 0;
  const int nb0 = std::min(lt_blocks_, cfg_.lt_wave_blocks);
  const int npool = std::max(nthreads, nlt);
  stats.resize(size_t(npool));
  if (lt_blocks_ > 0) lt_begin();
  std::atomic<int> next_block{0};
  // per thread the rays and walk steps its photons took (PassResult::lt_work_*)
  std::vector<uint64_t> lt_rays(size_t(npool), 0), lt_steps(size_t(npool), 0);
  auto worker = [&](int tid) {
    // Flush denormals to zero (Embree's advice; they only slow traversal down).
    _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
    _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
    if (tid < nthreads) tiles(tid);
    lt_blocks(next_block, 0, nb0, stats[size_t(tid)], lt_rays[size_t(tid)], lt_steps[size_t(tid)]);
  };

  std::vector<std::thread> pool;
  for (int t = 1; t < npool; ++t) pool.emplace_back(worker, t);
  worker(0);
  for (auto& th : pool) th.join();
  if (lt_blocks_ > 0 && !cancel_.load()) {
    lt_add(nb0);
    if (lt_blocks_ > cfg_.lt_wave_blocks) light_trace(stats, nlt, cfg_.lt_wave_blocks, lt_rays, lt_steps);
    for (size_t t = 0; t < lt_rays.size(); ++t) {
      result_.lt_work_rays += lt_rays[t];
      result_.lt_work_walk_steps += lt_steps[t];
    }
    // (once all waves are in: a pass cancelled before reports no photons)
    if (!cancel_.load()) result_.lt_photons = lt_photons_;
  }
  std::vector<std::vector<LightSplat>>().swap(lt_out_);   // (the job outlives the pass: result()'s views)
  for (const Stats& s : stats) result_.stats.merge(s);
  result_.cancelled = cancel_.load();
  result_.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  {
    std::lock_guard<std::mutex> lock(done_mutex_);
    done_.store(true);
  }
  done_cv_.notify_all();
}

// The light tracer's photons of the pass, in blocks of kLtBlock, each block's
// random stream keyed by (seed, pass, block, photon) and its splats kept apart
// and added in block order: the sums do not depend on the thread count.
// In waves of PassConfig::lt_wave_blocks blocks: the splats held at once stay
// bounded (at most one per photon, 16 bytes: 64 MiB a wave of 1024).
void RenderJob::lt_begin() {
  const Camera& cam = scene_->camera;
  const size_t npix = size_t(cam.crop_w) * size_t(cam.crop_h);
  result_.lt_sum.assign(npix * 3, 0.0);
  result_.lt_sum_sq.assign(npix * 3, 0.0);
  lt_out_.resize(static_cast<size_t>(std::min(lt_blocks_, cfg_.lt_wave_blocks)));
}

// Block wave + j into lt_out_[j].
void RenderJob::lt_block(int wave, int j, Stats& st) {
  const LightTracer& lt = *integrator_->light_tracer();
  const uint64_t b = uint64_t(wave + j);
  const uint64_t first = b * kLtBlock, last = std::min(lt_photons_, first + kLtBlock);
  std::vector<LightSplat>& out = lt_out_[size_t(j)];
  out.clear();
  for (uint64_t i = first; i < last; ++i) {
    // (pixel keys of the camera samples are below 2^63)
    PCG32 rng = make_stream(cfg_.seed, cfg_.pass, (uint64_t(1) << 63) | b, i - first);
    lt.trace(rng, st, out);
  }
  lt_blocks_done_.fetch_add(1);
}

// The splats of blocks lt_out_[0, nb), in block order.
void RenderJob::lt_add(int nb) {
  for (int j = 0; j < nb; ++j)
    for (const LightSplat& sp : lt_out_[size_t(j)])
      for (int c = 0; c < 3; ++c) {
        result_.lt_sum[size_t(sp.pixel) * 3 + c] += sp.value[c];
        result_.lt_sum_sq[size_t(sp.pixel) * 3 + c] += double(sp.value[c]) * sp.value[c];
      }
}

// Photon blocks wave + j, j = next++ < nb, until none is left or the pass is
// cancelled; adds the rays and walk steps they took to rays and steps.
void RenderJob::lt_blocks(std::atomic<int>& next, int wave, int nb, Stats& st, uint64_t& rays,
                          uint64_t& steps) {
  st.cancel = &cancel_;   // (the Bernoulli trials of camera-side chains poll it)
  auto traced = [&st] { return st.rays + st.shadow_rays + st.camera_rays + st.lt_rays; };
  for (;;) {
    if (cancel_.load(std::memory_order_relaxed)) return;
    const int j = next.fetch_add(1);
    if (j >= nb) return;
    const uint64_t r0 = traced(), w0 = st.walk_steps;
    lt_block(wave, j, st);
    rays += traced() - r0;
    steps += st.walk_steps - w0;
  }
}

// The waves from first_wave on, each in its own pool of nthreads (rays and
// steps per thread, as lt_blocks counts them).
void RenderJob::light_trace(std::vector<Stats>& stats, int nthreads, int first_wave,
                            std::vector<uint64_t>& rays, std::vector<uint64_t>& steps) {
  for (int wave = first_wave; wave < lt_blocks_; wave += cfg_.lt_wave_blocks) {
    const int nb = std::min(cfg_.lt_wave_blocks, lt_blocks_ - wave);
    std::atomic<int> next{0};
    auto worker = [&](int tid) {
      _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
      _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
      lt_blocks(next, wave, nb, stats[size_t(tid)], rays[size_t(tid)], steps[size_t(tid)]);
    };
    std::vector<std::thread> pool;
    for (int t = 1; t < nthreads; ++t) pool.emplace_back(worker, t);
    worker(0);
    for (auto& th : pool) th.join();
    if (cancel_.load()) return;
    lt_add(nb);
  }
}

PassResult render_pass(std::shared_ptr<const Scene> scene, std::shared_ptr<const Integrator> integrator,
                       const PassConfig& cfg) {
  RenderJob job(std::move(scene), std::move(integrator), cfg);
  job.start();
  while (!job.wait_for(3600.0)) {
  }
  return std::move(job.result());
}

}  // namespace mpg
