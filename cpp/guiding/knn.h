// Exact k-nearest-neighbour search in the normalised 6D (x_D, x_L) space: the
// KNN spatial structure of the MPG paper's ablation (Sec. 6.2 / Fig. 14,
// supplemental Sec. 3.3: a 6D kd-tree with accurate search, the chain
// distribution built from the neighbours on every query).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace mpg {

using std::size_t;

class KnnIndex {
 public:
  // `points`: n x 6 normalised coordinates (row-major). Point i has index i;
  // ties in distance are broken by the smaller index, so the neighbour set is
  // a function of the points and their indices only.
  void build(std::vector<float> points);
  size_t size() const { return pts_.size() / 6; }
  // The k nearest points of q (Euclidean, distances in double), sorted by index.
  void query(const float q[6], size_t k, std::vector<uint32_t>& out) const;
  size_t memory_bytes() const {
    return pts_.capacity() * sizeof(float) + idx_.capacity() * sizeof(uint32_t) + nodes_.capacity() * sizeof(Node);
  }

 private:
  struct Node {
    uint32_t begin, end;   // range in idx_
    int32_t child[2] = {-1, -1};
    int axis = -1;         // -1: a bucket
    float split = 0.f;
  };
  int build_rec(uint32_t b, uint32_t e);
  const float* pt(uint32_t i) const { return pts_.data() + size_t(i) * 6; }

  std::vector<float> pts_;      // by index during the build, then in tree order
  std::vector<uint32_t> idx_;
  std::vector<Node> nodes_;
};

}  // namespace mpg
