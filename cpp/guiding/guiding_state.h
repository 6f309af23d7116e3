// The guiding state: the spatial structure over the last iteration's
// sub-path samples and their chain distributions (MPG Secs. 5.5-5.6). Built from
// Python between training iterations; queried by the renderer (read-only,
// thread-safe). Two structures (paper Fig. 14, supplemental Sec. 3.3):
//  - stree (the paper's): the 6D STree, one ChainDistribution per leaf;
//  - knn: the exact k nearest samples of the query in the normalised 6D
//    space, a ChainDistribution built from them on every query (slow, as in
//    the paper; cached per thread for a repeated query).
// The result does not depend on the order of the samples nor on the number
// of threads.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "guiding/chain_distribution.h"
#include "guiding/knn.h"
#include "guiding/stree.h"

namespace mpg {

enum class GuideStructure { STree, Knn };
GuideStructure parse_guide_structure(const std::string& s);  // throws std::invalid_argument
const char* guide_structure_name(GuideStructure g);

struct GuideConfig {
  STreeConfig stree;       // c, epsilon, filter, threshold, max_depth, threads
  GuideStructure structure = GuideStructure::STree;
  int knn_k = 0;           // knn: neighbours per query; 0: ceil(c sqrt(|S|)), the STree's threshold
  // Lobes anchored at x_D + omega_D * anchor * |x_L - x_D| and aimed from the
  // query's x_D (ChainDistribution::build); 0: centred on omega_D (the paper's).
  float anchor = 0.f;
};
// Range checks of a configuration (throws std::invalid_argument naming the parameter).
void validate(const GuideConfig& cfg);

class GuidingState {
 public:
  void build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
             const GuideConfig& cfg);
  bool valid() const { return cfg_.structure == GuideStructure::Knn ? knn_.size() > 0 : !tree_.empty(); }
  const GuideConfig& config() const { return cfg_; }
  const STree& tree() const { return tree_; }
  // Distribution for (x_D, x_L), or nullptr when there is none: the STree leaf
  // holds no unfiltered sample (selective activation, MPG Sec. 5.8), or kNN
  // without samples. For knn the distribution lives in a per-thread cache: the
  // pointer stays valid until the next query() on the same thread.
  const ChainDistribution* query(const Vec3& xD, const Vec3& xL) const;
  const ChainDistribution& distribution(int leaf) const { return dists_[size_t(leaf)]; }
  // knn: the neighbours of (x_D, x_L), indices into knn_samples().
  void knn_neighbours(const Vec3& xD, const Vec3& xL, std::vector<uint32_t>& out) const;
  const std::vector<SubpathSample>& knn_samples() const { return knn_samples_; }
  int knn_k() const { return knn_k_; }
  size_t num_samples_stored() const {
    return cfg_.structure == GuideStructure::Knn ? knn_samples_.size() : tree_.num_samples_stored();
  }
  // The samples the guide was built from (each once, copies not counted).
  size_t num_samples_input() const {
    return cfg_.structure == GuideStructure::Knn ? knn_samples_.size() : tree_.samples().size();
  }
  double build_seconds() const { return build_seconds_; }
  // Bytes the built guide keeps (the structure, its samples and every leaf's
  // distribution; knn: its samples and kd-tree, the per-thread caches left out).
  size_t memory_bytes() const {
    size_t t = tree_.memory_bytes() + dists_.capacity() * sizeof(ChainDistribution) +
               knn_samples_.capacity() * sizeof(SubpathSample) + knn_.memory_bytes();
    for (const ChainDistribution& d : dists_) t += d.memory_bytes() - sizeof(ChainDistribution);
    return t;
  }
  double structure_seconds() const { return structure_seconds_; }  // the STree / kd-tree part of it
  void normalise(const Vec3& xD, const Vec3& xL, float out[6]) const { cube_.normalise(xD, xL, out); }

 private:
  GuideConfig cfg_;
  STree tree_;
  std::vector<ChainDistribution> dists_;
  // knn
  std::vector<SubpathSample> knn_samples_;  // canonical order
  KnnIndex knn_;
  Cube6 cube_;  // the normalisation (the same for both structures)
  int knn_k_ = 0;
  uint64_t generation_ = 0;  // identifies this build in the per-thread caches
  double build_seconds_ = 0.0, structure_seconds_ = 0.0;
};

}  // namespace mpg
