#include "guiding/stree.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <stdexcept>
#include <thread>

namespace mpg {

STreeFilter parse_stree_filter(const std::string& s) {
  if (s == "nearest") return STreeFilter::Nearest;
  if (s == "stochastic") return STreeFilter::Stochastic;
  if (s == "none") return STreeFilter::None;
  throw std::invalid_argument("unknown stree_filter '" + s + "' (expected nearest, stochastic or none)");
}

const char* stree_filter_name(STreeFilter f) {
  switch (f) {
    case STreeFilter::Nearest: return "nearest";
    case STreeFilter::Stochastic: return "stochastic";
    case STreeFilter::None: return "none";
  }
  return "?";
}

void Cube6::fit(const Vec3& bmin, const Vec3& bmax) {
  // "Cubified" scene bounds: one scale for all axes.
  const Vec3 ext = bmax - bmin;
  const float side = std::max(1e-6f, max_comp(ext)) * 1.0001f;
  origin = 0.5f * (bmin + bmax) - Vec3(0.5f * side);
  scale = 1.f / side;
}

struct STree::BuildNode {
  std::unique_ptr<BuildNode> child[2];
  uint8_t axis = 0;
  float split = 0.5f;
  Leaf leaf;
  bool is_leaf = false;
};

// A LIFO task queue run by a fixed number of threads: subtrees of large nodes
// become tasks, so two threads stay busy however unbalanced the tree is.
// Tasks write disjoint parts of the result, so the result does not depend on
// which thread runs what.
struct STree::TaskQueue {
  std::mutex m;
  std::condition_variable cv;
  std::vector<std::function<void()>> q;
  int pending = 0;  // queued + running
  bool parallel = false;

  void push(std::function<void()> f) {
    {
      std::lock_guard<std::mutex> l(m);
      q.push_back(std::move(f));
      ++pending;
    }
    cv.notify_one();
  }
  void work() {
    for (;;) {
      std::function<void()> f;
      {
        std::unique_lock<std::mutex> l(m);
        cv.wait(l, [&] { return !q.empty() || pending == 0; });
        if (q.empty()) return;
        f = std::move(q.back());
        q.pop_back();
      }
      f();
      std::lock_guard<std::mutex> l(m);
      if (--pending == 0) cv.notify_all();
    }
  }
  void run(int threads) {
    std::vector<std::thread> pool;
    for (int t = 1; t < threads; ++t) pool.emplace_back([this] { work(); });
    work();
    for (auto& th : pool) th.join();
  }
};

namespace {
constexpr uint32_t kTaskMin = 8192;  // nodes with fewer unfiltered samples are not split into tasks

// Per-sample jitter in [-1, 1) for axis `a`, a function of the content only.
inline float jitter(uint64_t key, int a) {
  return float(mix64(key + uint64_t(a) * 0x9e3779b97f4a7c15ULL) >> 40) * (2.f / float(1 << 24)) - 1.f;
}

template <typename F>
void parallel_for(size_t n, int threads, F&& f) {
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t i; (i = next.fetch_add(1)) < n;) f(i);
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < std::max(1, threads); ++t) pool.emplace_back(work);
  work();
  for (auto& th : pool) th.join();
}
}  // namespace

// Sorts the input by (6D Morton code, content hash, bytes) into samples_.
// Level d of the tree splits axis d % 6 at the midpoint of the node's
// interval, i.e. on bit (B - 1 - d / 6) of the coordinate quantised to B bits
// (exact: the quantisation multiplies by a power of two), so the code's
// bit (6B - 1 - d) is the side at depth d, and the samples of every node are
// a contiguous range of the sorted array.
void STree::sort_samples(const std::vector<SubpathSample>& in) {
  const size_t N = in.size();
  const int B = std::clamp((cfg_.max_depth + 5) / 6, 1, 10);
  code_bits_ = B;
  const uint32_t qmax = (1u << B) - 1;
  // spread[a][q]: the bits of q at axis a's code positions (bit j of q is
  // split at depth d = (B - 1 - j) * 6 + a, code bit 6B - 1 - d)
  std::vector<uint64_t> spread(size_t(6) << B, 0);
  for (int a = 0; a < 6; ++a)
    for (uint32_t q = 0; q <= qmax; ++q) {
      uint64_t c = 0;
      for (int j = 0; j < B; ++j)
        if ((q >> j) & 1u) c |= uint64_t(1) << (6 * B - 1 - ((B - 1 - j) * 6 + a));
      spread[(size_t(a) << B) + q] = c;
    }
  struct Item { uint64_t code; uint32_t idx; };
  std::vector<Item> items(N), tmp(N);
  std::vector<uint64_t> keys(N);
  const float qscale = float(1u << B);
  const size_t chunk = 1 << 15;
  const size_t nchunks = (N + chunk - 1) / chunk;
  parallel_for(nchunks, cfg_.threads, [&](size_t ci) {
    for (size_t i = ci * chunk; i < std::min(N, (ci + 1) * chunk); ++i) {
      uint64_t c = 0;
      for (int a = 0; a < 6; ++a) {
        const float x = cube_.coord(in[i], a) * qscale;
        // x < 0 -> 0, x >= 2^B or NaN -> qmax: the sides `coord < mid` picks
        const uint32_t q = x < 0.f ? 0u : (x < qscale ? uint32_t(x) : qmax);
        c |= spread[(size_t(a) << B) + q];
      }
      items[i] = {c, uint32_t(i)};
      keys[i] = content_key(in[i]);
    }
  });
  // LSD radix sort on the 6B code bits, 12 bits per pass (stable)
  for (int shift = 0; shift < 6 * B; shift += 12) {
    std::vector<uint32_t> count(4097, 0);
    for (const Item& it : items) count[((it.code >> shift) & 4095) + 1]++;
    for (size_t i = 1; i < count.size(); ++i) count[i] += count[i - 1];
    for (const Item& it : items) tmp[count[(it.code >> shift) & 4095]++] = it;
    items.swap(tmp);
  }
  // equal codes: canonical order by content
  for (size_t i = 0; i < N;) {
    size_t j = i + 1;
    while (j < N && items[j].code == items[i].code) ++j;
    if (j - i > 1)
      std::sort(items.begin() + std::ptrdiff_t(i), items.begin() + std::ptrdiff_t(j), [&](const Item& a, const Item& b) {
        return canonical_less(keys[a.idx], in[a.idx], keys[b.idx], in[b.idx]);
      });
    i = j;
  }
  samples_.resize(N);
  codes_.resize(N);
  for (auto& c : coords_) c.resize(N);
  parallel_for(nchunks, cfg_.threads, [&](size_t ci) {
    const size_t end = std::min(N, (ci + 1) * chunk);
    for (size_t i = ci * chunk; i < end; ++i) {
      if (i + 16 < end) __builtin_prefetch(&in[items[i + 16].idx]);
      SubpathSample s = in[items[i].idx];
      s.flags = uint8_t(s.flags & ~SubpathSample::kFiltered);
      samples_[i] = s;
      codes_[i] = items[i].code;
      for (int a = 0; a < 6; ++a) coords_[a][i] = cube_.coord(s, a);
    }
  });
}

// A node: the unfiltered samples samples_[b, e) and the filtered copies `filt`
// (indices into samples_).
void STree::build_rec(BuildNode& node, uint32_t b, uint32_t e, std::vector<uint32_t> filt, int depth,
                      const float lo[6], const float hi[6], TaskQueue& tq) {
  const uint32_t k = e - b;  // only unfiltered samples count (supplemental Sec. 3.3)
  if (float(k) <= threshold_ || depth >= std::min(cfg_.max_depth, 6 * code_bits_)) {
    node.is_leaf = true;
    Leaf& l = node.leaf;
    l.depth = depth;
    std::copy(lo, lo + 6, l.lo);
    std::copy(hi, hi + 6, l.hi);
    l.begin = b;
    l.unfiltered = int(k);
    l.filtered = std::move(filt);
    // in memory order (a canonical order too): reading them is faster
    std::sort(l.filtered.begin(), l.filtered.end());
    return;
  }
  const int axis = depth % 6;
  const float mid = 0.5f * (lo[axis] + hi[axis]);
  node.axis = uint8_t(axis);
  node.split = mid;
  float clo[2][6], chi[2][6];
  for (int c = 0; c < 2; ++c) {
    std::copy(lo, lo + 6, clo[c]);
    std::copy(hi, hi + 6, chi[c]);
  }
  chi[0][axis] = mid;
  clo[1][axis] = mid;
  const int pos = 6 * code_bits_ - 1 - depth;
  const uint32_t p = uint32_t(std::partition_point(codes_.begin() + b, codes_.begin() + e,
                                                   [&](uint64_t c) { return ((c >> pos) & 1u) == 0; }) -
                              codes_.begin());

  std::vector<uint32_t> cf[2];
  const float eps = cfg_.filter == STreeFilter::Nearest ? cfg_.epsilon : 0.f;
  // Margin of each child on the split axis: a filtered sample farther than
  // 2 eps x the child's extent from the child's box is dropped.
  const float margin[2] = {2.f * eps * (mid - lo[axis]), 2.f * eps * (hi[axis] - mid)};
  if (eps > 0.f) {
    const float* X = coords_[axis].data();
    // Inherited copies: by side, the far ones dropped (only the split axis
    // changes the box, so only it needs checking).
    for (uint32_t i : filt) {
      const float v = X[i];
      const int c = v < mid ? 0 : 1;
      const float d = c == 0 ? lo[axis] - v : v - hi[axis];
      if (d <= margin[c]) cf[c].push_back(i);
    }
    // New copies: the floor(eps k) unfiltered samples of each side nearest the
    // plane go to the other child (supplemental Sec. 3.3) - those within the
    // other child's margin, as farther ones would be dropped there at once.
    const size_t m = size_t(std::floor(eps * float(k)));
    const uint32_t range[2][2] = {{b, p}, {p, e}};
    std::vector<uint32_t> cand;
    for (int c = 0; c < 2 && m > 0; ++c) {
      const int o = 1 - c;
      cand.clear();
      for (uint32_t i = range[c][0]; i < range[c][1]; ++i)
        if (std::abs(X[i] - mid) <= margin[o]) cand.push_back(i);
      if (cand.size() > m) {
        // nearest first; ties by position in the canonical order
        std::nth_element(cand.begin(), cand.begin() + std::ptrdiff_t(m), cand.end(), [&](uint32_t x, uint32_t y) {
          const float dx = std::abs(X[x] - mid), dy = std::abs(X[y] - mid);
          return dx < dy || (dx == dy && x < y);
        });
        cand.resize(m);
      }
      cf[o].insert(cf[o].end(), cand.begin(), cand.end());
    }
  }
  filt.clear();
  filt.shrink_to_fit();

  node.child[0] = std::make_unique<BuildNode>();
  node.child[1] = std::make_unique<BuildNode>();
  BuildNode* c0 = node.child[0].get();
  BuildNode* c1 = node.child[1].get();
  if (tq.parallel && e - p >= kTaskMin && p - b >= kTaskMin) {
    // the right subtree as a task (boxes copied into the closure)
    struct Box { float lo[6], hi[6]; } box;
    std::copy(clo[1], clo[1] + 6, box.lo);
    std::copy(chi[1], chi[1] + 6, box.hi);
    auto f1 = std::make_shared<std::vector<uint32_t>>(std::move(cf[1]));
    tq.push([this, c1, p, e, f1, depth, box, &tq]() mutable {
      build_rec(*c1, p, e, std::move(*f1), depth + 1, box.lo, box.hi, tq);
    });
    build_rec(*c0, b, p, std::move(cf[0]), depth + 1, clo[0], chi[0], tq);
  } else {
    build_rec(*c0, b, p, std::move(cf[0]), depth + 1, clo[0], chi[0], tq);
    build_rec(*c1, p, e, std::move(cf[1]), depth + 1, clo[1], chi[1], tq);
  }
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

// Stochastic filtering (Mueller 2019, "Practical Path Guiding" in Production,
// as the MPG paper's StochasticFilter ablation): every sample is jittered once,
// uniformly within +-eps x its leaf's extent on each axis, and moved to the
// leaf holding the jittered position. No copies.
void STree::stochastic_regroup() {
  const size_t L = leaves_.size();
  std::vector<uint32_t> dest(samples_.size());
  parallel_for(L, cfg_.threads, [&](size_t li) {
    const Leaf& l = leaves_[li];
    for (uint32_t i = l.begin; i < l.begin + uint32_t(l.unfiltered); ++i) {
      const SubpathSample& s = samples_[i];
      const uint64_t key = content_key(s);
      float q[6];
      for (int a = 0; a < 6; ++a) q[a] = cube_.coord(s, a) + jitter(key, a) * cfg_.epsilon * (l.hi[a] - l.lo[a]);
      dest[i] = uint32_t(leaf_of_normalised(q));
    }
  });
  std::vector<uint32_t> offset(L + 1, 0);
  for (uint32_t d : dest) offset[d + 1]++;
  for (size_t i = 0; i < L; ++i) offset[i + 1] += offset[i];
  for (size_t i = 0; i < L; ++i) {
    leaves_[i].begin = offset[i];
    leaves_[i].unfiltered = int(offset[i + 1] - offset[i]);
  }
  // stable: every leaf keeps the canonical order
  std::vector<SubpathSample> out(samples_.size());
  for (size_t i = 0; i < samples_.size(); ++i) out[offset[dest[i]]++] = samples_[i];
  samples_ = std::move(out);
}

void STree::build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
                  const STreeConfig& cfg) {
  cfg_ = cfg;
  nodes_.clear();
  leaves_.clear();
  cube_.fit(bmin, bmax);
  threshold_ = cfg.threshold > 0 ? float(cfg.threshold) : std::max(1.f, cfg.c * std::sqrt(float(samples.size())));
  sort_samples(samples);
  const float lo[6] = {0, 0, 0, 0, 0, 0}, hi[6] = {1, 1, 1, 1, 1, 1};
  BuildNode root;
  TaskQueue tq;
  tq.parallel = cfg.threads > 1;
  tq.push([&] { build_rec(root, 0, uint32_t(samples_.size()), {}, 0, lo, hi, tq); });
  tq.run(std::max(1, cfg.threads));
  flatten(root);
  build_top();
  codes_ = {};
  for (auto& c : coords_) c = {};
  if (cfg_.filter == STreeFilter::Stochastic && cfg_.epsilon > 0.f) stochastic_regroup();
}

int STree::descend(int n, const float q[6]) const {
  if (nodes_.empty()) return -1;
  while (nodes_[size_t(n)].leaf < 0) {
    const Node& nd = nodes_[size_t(n)];
    n = nd.child[q[nd.axis] < nd.split ? 0 : 1];
  }
  return nodes_[size_t(n)].leaf;
}

namespace {
// The cell 0..3 of q on one axis between the grid lines 1/4, 1/2, 3/4, with
// the descent's own test (q < split: left): NaN and q >= 3/4 land in 3 as
// they go right at every split.
inline int grid_cell(float q) { return q < 0.5f ? (q < 0.25f ? 0 : 1) : (q < 0.75f ? 2 : 3); }
inline bool on_grid(float s) { return s == 0.25f || s == 0.5f || s == 0.75f; }
}  // namespace

void STree::build_top() {
  top_.assign(nodes_.empty() ? 0 : size_t(1) << 12, 0);
  for (size_t cell = 0; cell < top_.size(); ++cell) {
    float c[6];  // the cell's centre: on the same side of every grid line as the whole cell
    for (int a = 0; a < 6; ++a) c[a] = (float((cell >> (2 * a)) & 3u) + 0.5f) * 0.25f;
    int n = 0;
    while (nodes_[size_t(n)].leaf < 0 && on_grid(nodes_[size_t(n)].split)) {
      const Node& nd = nodes_[size_t(n)];
      n = nd.child[c[nd.axis] < nd.split ? 0 : 1];
    }
    top_[cell] = n;
  }
}

int STree::leaf_of_normalised(const float q[6]) const {
  if (nodes_.empty()) return -1;
  size_t cell = 0;
  for (int a = 0; a < 6; ++a) cell |= size_t(grid_cell(q[a])) << (2 * a);
  return descend(top_[cell], q);
}

int STree::leaf_of(const Vec3& xD, const Vec3& xL) const {
  float q[6];
  normalise(xD, xL, q);
  return leaf_of_normalised(q);
}

size_t STree::memory_bytes() const {
  size_t t = nodes_.capacity() * sizeof(Node) + top_.capacity() * sizeof(int) +
             leaves_.capacity() * sizeof(Leaf) + samples_.capacity() * sizeof(SubpathSample);
  for (const Leaf& l : leaves_) t += l.filtered.capacity() * sizeof(uint32_t);
  for (const auto& c : coords_) t += c.capacity() * sizeof(float);
  return t + codes_.capacity() * sizeof(uint64_t);
}

size_t STree::num_samples_stored() const {
  size_t t = 0;
  for (const Leaf& l : leaves_) t += l.size();
  return t;
}

}  // namespace mpg
