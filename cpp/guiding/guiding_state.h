// The guiding state: an STree over the last iteration's sub-path samples and
// one ChainDistribution per leaf. Built from Python between training
// iterations; queried by the renderer (read-only, thread-safe).
#pragma once

#include <vector>

#include "guiding/chain_distribution.h"
#include "guiding/stree.h"

namespace mpg {

class GuidingState {
 public:
  void build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
             const STreeConfig& cfg, int threads = 2);
  bool valid() const { return !tree_.empty(); }
  const STree& tree() const { return tree_; }
  // Distribution of the leaf of (x_D, x_L), or nullptr when the leaf holds no
  // unfiltered sample (selective activation, MPG Sec. 5.8).
  const ChainDistribution* query(const Vec3& xD, const Vec3& xL) const;
  const ChainDistribution& distribution(int leaf) const { return dists_[size_t(leaf)]; }
  double build_seconds() const { return build_seconds_; }

 private:
  STree tree_;
  std::vector<ChainDistribution> dists_;
  double build_seconds_ = 0.0;
};

}  // namespace mpg
