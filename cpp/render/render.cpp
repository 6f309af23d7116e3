#include "render/render.h"

#include <xmmintrin.h>
#include <pmmintrin.h>

#include <chrono>

#include "core/rng.h"

namespace mpg {

RenderJob::RenderJob(std::shared_ptr<const Scene> scene, std::shared_ptr<const Integrator> integrator,
                     PassConfig cfg)
    : scene_(std::move(scene)), integrator_(std::move(integrator)), cfg_(cfg) {
  const Camera& c = scene_->camera;
  const int tx = (c.crop_w + cfg_.tile - 1) / cfg_.tile, ty = (c.crop_h + cfg_.tile - 1) / cfg_.tile;
  tiles_total_ = std::max(1, tx * ty);
}

RenderJob::~RenderJob() {
  cancel_.store(true);
  if (thread_.joinable()) thread_.join();
}

void RenderJob::start() { thread_ = std::thread([this] { run(); }); }

bool RenderJob::wait_for(double seconds) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (!done_.load()) {
    if (std::chrono::steady_clock::now() >= until) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  if (thread_.joinable()) thread_.join();
  return true;
}

double RenderJob::progress() const { return double(tiles_done_.load()) / double(tiles_total_); }

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
  int nthreads = cfg_.threads > 0 ? cfg_.threads : int(std::thread::hardware_concurrency());
  nthreads = std::max(1, std::min(nthreads, tiles_total_));
  std::atomic<int> next_tile{0};
  std::vector<Stats> stats(static_cast<size_t>(nthreads));

  auto worker = [&](int tid) {
    // Flush denormals to zero (Embree's advice; they only slow traversal down).
    _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
    _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
    Stats& st = stats[size_t(tid)];
    std::vector<double> tile_sum, tile_sq;
    for (;;) {
      if (cancel_.load(std::memory_order_relaxed)) return;
      const int tile = next_tile.fetch_add(1);
      if (tile >= tiles_total_) return;
      const int x0 = (tile % tx) * T, y0 = (tile / tx) * T;
      const int x1 = std::min(x0 + T, W), y1 = std::min(y0 + T, H);
      // Camera rays are traced as 4x4 packets (coherent: Embree's packet
      // traversal is much faster for them); each lane then continues alone.
      const int tw = x1 - x0, th = y1 - y0;
      std::vector<double>& s = tile_sum;
      std::vector<double>& s2 = tile_sq;
      s.assign(size_t(tw) * th * 3, 0.0);
      s2.assign(size_t(tw) * th * 3, 0.0);
      for (int k = 0; k < cfg_.spp; ++k) {
        for (int by = y0; by < y1; by += 4) {
          for (int bx = x0; bx < x1; bx += 4) {
            PCG32 rng[16];
            Vec3 o[16], d[16];
            float tmin[16], tmax[16];
            int px[16], py[16];
            int n = 0;
            for (int y = by; y < std::min(by + 4, y1); ++y) {
              for (int x = bx; x < std::min(bx + 4, x1); ++x) {
                const int fx = cam.crop_x + x, fy = cam.crop_y + y;
                const uint64_t pixel = uint64_t(fy) * uint64_t(cam.width) + uint64_t(fx);
                rng[n] = make_stream(cfg_.seed, cfg_.pass, pixel, uint64_t(k));
                const float ox = cam.filter.sample(rng[n].next_float());
                const float oy = cam.filter.sample(rng[n].next_float());
                cam.generate_ray(Vec2(float(fx) + 0.5f + ox, float(fy) + 0.5f + oy), o[n], d[n], tmin[n], tmax[n]);
                px[n] = x - x0;
                py[n] = y - y0;
                ++n;
              }
            }
            SurfaceInteraction hits[16];
            scene.intersect16(o, d, tmin, tmax, n, hits);
            st.rays += uint64_t(n);
            st.camera_rays += uint64_t(n);
            for (int i = 0; i < n; ++i) {
              Color L = integrator_->Li_hit(scene, o[i], d[i], hits[i], rng[i], st);
              st.samples++;
              if (!(std::isfinite(L.x) && std::isfinite(L.y) && std::isfinite(L.z))) {
                if (std::isnan(L.x) || std::isnan(L.y) || std::isnan(L.z)) st.rejected_nan++;
                else st.rejected_inf++;
                L = Color(0.f);
              } else if (L.x < 0.f || L.y < 0.f || L.z < 0.f) {
                st.rejected_negative++;
                L = Color(0.f);
              }
              const size_t j = (size_t(py[i]) * tw + px[i]) * 3;
              for (int c = 0; c < 3; ++c) {
                s[j + c] += L[c];
                s2[j + c] += double(L[c]) * L[c];
              }
            }
          }
        }
      }
      for (int y = 0; y < th; ++y) {
        for (int x = 0; x < tw; ++x) {
          const size_t i = (size_t(y0 + y) * W + (x0 + x)) * 3, j = (size_t(y) * tw + x) * 3;
          for (int c = 0; c < 3; ++c) {
            result_.sum[i + c] = s[j + c];
            result_.sum_sq[i + c] = s2[j + c];
          }
        }
      }
      tiles_done_.fetch_add(1);
    }
  };

  std::vector<std::thread> pool;
  for (int t = 1; t < nthreads; ++t) pool.emplace_back(worker, t);
  worker(0);
  for (auto& th : pool) th.join();
  for (const Stats& s : stats) result_.stats.merge(s);
  result_.cancelled = cancel_.load();
  result_.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  done_.store(true);
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
