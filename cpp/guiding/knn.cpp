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
  auto visit = [&](uint32_t i) {
    const float* p = pt(i);
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
  // depth-first, nearer child first; a far child is visited while its slab
  // can hold a point at a distance <= the current k-th (ties by index).
  struct Item { int node; double d; };
  Item stack[128];
  int sp = 0;
  stack[sp++] = {0, 0.0};
  while (sp > 0) {
    const Item it = stack[--sp];
    if (it.d > worst()) continue;
    const Node& nd = nodes_[size_t(it.node)];
    if (nd.axis < 0) {
      for (uint32_t j = nd.begin; j < nd.end; ++j) visit(idx_[j]);
      continue;
    }
    const double t = double(q[nd.axis]) - double(nd.split);
    const int near = t < 0.0 ? 0 : 1;
    stack[sp++] = {nd.child[1 - near], std::max(it.d, t * t)};
    stack[sp++] = {nd.child[near], it.d};
  }
  out.resize(heap.size());
  for (size_t i = 0; i < heap.size(); ++i) out[i] = heap[i].second;
  std::sort(out.begin(), out.end());
}

}  // namespace mpg
