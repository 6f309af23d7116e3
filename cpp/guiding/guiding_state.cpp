#include "guiding/guiding_state.h"

#include <atomic>
#include <chrono>
#include <thread>

namespace mpg {

void GuidingState::build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
                         const STreeConfig& cfg, int threads) {
  const auto t0 = std::chrono::steady_clock::now();
  tree_.build(samples, bmin, bmax, cfg);
  dists_.assign(tree_.num_leaves(), ChainDistribution());
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t i; (i = next.fetch_add(1)) < dists_.size();) dists_[i].build(tree_.leaf(int(i)).samples);
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < std::max(1, threads); ++t) pool.emplace_back(work);
  work();
  for (auto& th : pool) th.join();
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

const ChainDistribution* GuidingState::query(const Vec3& xD, const Vec3& xL) const {
  const int l = tree_.leaf_of(xD, xL);
  if (l < 0 || tree_.leaf(l).unfiltered == 0) return nullptr;
  return &dists_[size_t(l)];
}

}  // namespace mpg
