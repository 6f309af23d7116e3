#include "guiding/stree.h"

#include <algorithm>
#include <cmath>
#include <future>

namespace mpg {

struct STree::BuildNode {
  std::unique_ptr<BuildNode> child[2];
  uint8_t axis = 0;
  float split = 0.5f;
  Leaf leaf;
  bool is_leaf = false;
};

void STree::normalise(const Vec3& xD, const Vec3& xL, float out[6]) const {
  const Vec3 a = (xD - origin_) * scale_, b = (xL - origin_) * scale_;
  out[0] = a.x; out[1] = a.y; out[2] = a.z;
  out[3] = b.x; out[4] = b.y; out[5] = b.z;
}

namespace {
inline float coord(const SubpathSample& s, int axis, const Vec3& origin, float scale) {
  return axis < 3 ? (s.xD[axis] - origin[axis]) * scale : (s.xL[axis - 3] - origin[axis - 3]) * scale;
}
}  // namespace

std::unique_ptr<STree::BuildNode> STree::build_rec(std::vector<SubpathSample> s, int depth,
                                                   const float lo[6], const float hi[6]) const {
  auto node = std::make_unique<BuildNode>();
  if (float(s.size()) <= threshold_ || depth >= cfg_.max_depth) {
    node->is_leaf = true;
    Leaf& l = node->leaf;
    l.depth = depth;
    std::copy(lo, lo + 6, l.lo);
    std::copy(hi, hi + 6, l.hi);
    l.unfiltered = int(std::count_if(s.begin(), s.end(), [](const SubpathSample& x) { return !x.filtered(); }));
    l.samples = std::move(s);
    return node;
  }
  const int axis = depth % 6;
  const float mid = 0.5f * (lo[axis] + hi[axis]);
  node->axis = uint8_t(axis);
  node->split = mid;
  std::vector<SubpathSample> side[2];
  for (const SubpathSample& x : s) side[coord(x, axis, origin_, scale_) < mid ? 0 : 1].push_back(x);
  const size_t k = s.size();
  s.clear();
  s.shrink_to_fit();
  // epsilon-overlap filtering: copy the floor(eps k) samples nearest the split
  // plane from each side to the other, marked as filtered copies.
  const size_t m = size_t(std::floor(cfg_.epsilon * float(k)));
  std::vector<SubpathSample> copy[2];
  if (m > 0) {
    for (int c = 0; c < 2; ++c) {
      std::vector<SubpathSample>& v = side[c];
      const size_t take = std::min(m, v.size());
      auto dist = [&](const SubpathSample& x) { return std::abs(coord(x, axis, origin_, scale_) - mid); };
      std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(take), v.end(),
                       [&](const SubpathSample& a, const SubpathSample& b) { return dist(a) < dist(b); });
      copy[1 - c].assign(v.begin(), v.begin() + std::ptrdiff_t(take));
      for (auto& x : copy[1 - c]) x.flags |= SubpathSample::kFiltered;
    }
  }
  float clo[2][6], chi[2][6];
  for (int c = 0; c < 2; ++c) {
    std::copy(lo, lo + 6, clo[c]);
    std::copy(hi, hi + 6, chi[c]);
  }
  chi[0][axis] = mid;
  clo[1][axis] = mid;
  for (int c = 0; c < 2; ++c) {
    side[c].insert(side[c].end(), copy[c].begin(), copy[c].end());
    // drop (filtered) samples farther than 2 eps x the extent from the child's box
    if (cfg_.epsilon > 0.f) {
      const float* l = clo[c];
      const float* h = chi[c];
      auto far = [&](const SubpathSample& x) {
        if (!x.filtered()) return false;
        for (int a = 0; a < 6; ++a) {
          const float v = coord(x, a, origin_, scale_);
          const float d = std::max({l[a] - v, 0.f, v - h[a]});
          if (d > 2.f * cfg_.epsilon * (h[a] - l[a])) return true;
        }
        return false;
      };
      side[c].erase(std::remove_if(side[c].begin(), side[c].end(), far), side[c].end());
    }
  }
  if (depth < cfg_.parallel_depth) {
    auto left = std::async(std::launch::async, [&] { return build_rec(std::move(side[0]), depth + 1, clo[0], chi[0]); });
    node->child[1] = build_rec(std::move(side[1]), depth + 1, clo[1], chi[1]);
    node->child[0] = left.get();
  } else {
    node->child[0] = build_rec(std::move(side[0]), depth + 1, clo[0], chi[0]);
    node->child[1] = build_rec(std::move(side[1]), depth + 1, clo[1], chi[1]);
  }
  return node;
}

int STree::flatten(BuildNode& b) {
  const int id = int(nodes_.size());
  nodes_.emplace_back();
  if (b.is_leaf) {
    nodes_[size_t(id)].leaf = int(leaves_.size());
    leaves_.push_back(std::move(b.leaf));
    return id;
  }
  nodes_[size_t(id)].axis = b.axis;
  nodes_[size_t(id)].split = b.split;
  const int l = flatten(*b.child[0]);
  const int r = flatten(*b.child[1]);
  nodes_[size_t(id)].child[0] = l;
  nodes_[size_t(id)].child[1] = r;
  return id;
}

void STree::build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
                  const STreeConfig& cfg) {
  cfg_ = cfg;
  nodes_.clear();
  leaves_.clear();
  // "Cubified" scene bounds: one scale for all axes.
  const Vec3 ext = bmax - bmin;
  const float side = std::max(1e-6f, max_comp(ext)) * 1.0001f;
  origin_ = 0.5f * (bmin + bmax) - Vec3(0.5f * side);
  scale_ = 1.f / side;
  threshold_ = std::max(1.f, cfg.c * std::sqrt(float(samples.size())));
  std::vector<SubpathSample> s(samples);
  for (auto& x : s) x.flags = uint8_t(x.flags & ~SubpathSample::kFiltered);
  const float lo[6] = {0, 0, 0, 0, 0, 0}, hi[6] = {1, 1, 1, 1, 1, 1};
  auto root = build_rec(std::move(s), 0, lo, hi);
  flatten(*root);
}

int STree::leaf_of(const Vec3& xD, const Vec3& xL) const {
  if (nodes_.empty()) return -1;
  float q[6];
  normalise(xD, xL, q);
  int n = 0;
  while (nodes_[size_t(n)].leaf < 0) {
    const Node& nd = nodes_[size_t(n)];
    n = nd.child[q[nd.axis] < nd.split ? 0 : 1];
  }
  return nodes_[size_t(n)].leaf;
}

size_t STree::num_samples_stored() const {
  size_t t = 0;
  for (const Leaf& l : leaves_) t += l.samples.size();
  return t;
}

}  // namespace mpg
