#include "guiding/knn.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

namespace mpg {

namespace {
constexpr uint32_t kBucket = 16;
}

void KnnIndex::build(std::vector<float> points) {
  pts_ = std::move(points);
  const uint32_t n = uint32_t(size());
  idx_.resize(n);
  for (uint32_t i = 0; i < n; ++i) idx_[i] = i;
  nodes_.clear();
  nodes_.reserve(2 * (n / kBucket + 1));
  if (n > 0) build_rec(0, n);
  // points in tree order: a bucket's points are contiguous
  std::vector<float> sorted(pts_.size());
  for (uint32_t j = 0; j < n; ++j) std::copy(pt(idx_[j]), pt(idx_[j]) + 6, sorted.data() + size_t(j) * 6);
  pts_.swap(sorted);
}

// Median split along the axis of largest spread.
int KnnIndex::build_rec(uint32_t b, uint32_t e) {
  const int id = int(nodes_.size());
  nodes_.push_back(Node{b, e});
  if (e - b <= kBucket) return id;
  float lo[6], hi[6];
  std::fill(lo, lo + 6, std::numeric_limits<float>::infinity());
  std::fill(hi, hi + 6, -std::numeric_limits<float>::infinity());
  for (uint32_t i = b; i < e; ++i) {
    const float* p = pt(idx_[i]);
    for (int a = 0; a < 6; ++a) {
      lo[a] = std::min(lo[a], p[a]);
      hi[a] = std::max(hi[a], p[a]);
    }
  }
  int axis = 0;
  for (int a = 1; a < 6; ++a)
    if (hi[a] - lo[a] > hi[axis] - lo[axis]) axis = a;
  if (!(hi[axis] > lo[axis])) return id;  // all points equal: one bucket
  const uint32_t m = b + (e - b) / 2;
  std::nth_element(idx_.begin() + b, idx_.begin() + m, idx_.begin() + e, [&](uint32_t x, uint32_t y) {
    const float px = pt(x)[axis], py = pt(y)[axis];
    return px < py || (px == py && x < y);
  });
  // left: [b, m) with coord <= split; right: [m, e) with coord >= split
  const float split = pt(idx_[m])[axis];
  nodes_[size_t(id)].axis = axis;
  nodes_[size_t(id)].split = split;
  const int l = build_rec(b, m);
  const int r = build_rec(m, e);
  nodes_[size_t(id)].child[0] = l;
  nodes_[size_t(id)].child[1] = r;
  return id;
}

void KnnIndex::query(const float q[6], size_t k, std::vector<uint32_t>& out) const {
  out.clear();
  k = std::min(k, size());
  if (k == 0) return;
  // max-heap of (squared distance, index): the worst of the current k on top
  using Cand = std::pair<double, uint32_t>;
  std::vector<Cand> heap;
  heap.reserve(k + 1);
  auto visit = [&](uint32_t j) {  // position j in tree order
    const float* p = pt(j);
    const uint32_t i = idx_[j];
    double d = 0.0;
    for (int a = 0; a < 6; ++a) {
      const double t = double(p[a]) - double(q[a]);
      d += t * t;
    }
    const Cand c{d, i};
    if (heap.size() < k) {
      heap.push_back(c);
      std::push_heap(heap.begin(), heap.end());
    } else if (c < heap.front()) {
      std::pop_heap(heap.begin(), heap.end());
      heap.back() = c;
      std::push_heap(heap.begin(), heap.end());
    }
  };
  auto worst = [&] { return heap.size() < k ? std::numeric_limits<double>::infinity() : heap.front().first; };
  // Depth-first, nearer child first, with the incremental distance of Arya &
  // Mount (rd = squared distance from q to the cell, off[a] its per-axis
  // part): a far child is visited while rd <= the current k-th distance
  // (<=: ties are broken by index).
  double off[6] = {0, 0, 0, 0, 0, 0};
  auto search = [&](auto&& self, int node, double rd) -> void {
    const Node& nd = nodes_[size_t(node)];
    if (nd.axis < 0) {
      for (uint32_t j = nd.begin; j < nd.end; ++j) visit(j);
      return;
    }
    const double t = double(q[nd.axis]) - double(nd.split);
    const int near = t < 0.0 ? 0 : 1;
    self(self, nd.child[near], rd);
    const double old = off[nd.axis];
    const double rd2 = rd - old * old + t * t;
    if (rd2 <= worst() * (1.0 + 1e-12)) {  // (margin for the rounding of rd)
      off[nd.axis] = t;
      self(self, nd.child[1 - near], rd2);
      off[nd.axis] = old;
    }
  };
  search(search, 0, 0.0);
  out.resize(heap.size());
  for (size_t i = 0; i < heap.size(); ++i) out[i] = heap[i].second;
  std::sort(out.begin(), out.end());
}

}  // namespace mpg
