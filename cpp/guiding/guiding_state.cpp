#include "guiding/guiding_state.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <thread>

namespace mpg {

GuideStructure parse_guide_structure(const std::string& s) {
  if (s == "stree") return GuideStructure::STree;
  if (s == "knn") return GuideStructure::Knn;
  throw std::invalid_argument("unknown guide_structure '" + s + "' (expected stree or knn)");
}

const char* guide_structure_name(GuideStructure g) { return g == GuideStructure::Knn ? "knn" : "stree"; }

namespace {
std::atomic<uint64_t> g_generation{0};

struct KnnCache {
  const GuidingState* owner = nullptr;
  uint64_t generation = 0;
  float q[6] = {};
  bool has = false;
  ChainDistribution dist;
  std::vector<uint32_t> idx, next;  // neighbours of the cached / the new query
  std::vector<SubpathSample> buf;
};
}  // namespace

void validate(const GuideConfig& cfg) {
  const STreeConfig& sc = cfg.stree;
  auto bad = [](const std::string& what, const std::string& got) {
    throw std::invalid_argument(what + ", got " + got);
  };
  if (!(sc.epsilon >= 0.f && sc.epsilon < 0.5f)) bad("stree_epsilon must be in [0, 0.5)", std::to_string(sc.epsilon));
  if (!(sc.c > 0.f)) bad("stree_c must be positive", std::to_string(sc.c));
  if (sc.threshold < 0) bad("stree_threshold must be >= 0 (0: c sqrt(|S|))", std::to_string(sc.threshold));
  if (sc.max_depth < 0) bad("max_depth must be >= 0", std::to_string(sc.max_depth));
  if (cfg.knn_k < 0) bad("knn_k must be >= 0 (0: c sqrt(|S|))", std::to_string(cfg.knn_k));
  // (an anchor far beyond the scene aims every lobe as its direction does, up
  // to rounding; past ~1e30 the anchor overflows and every centre is +z)
  if (!((cfg.anchor >= 0.f && cfg.anchor <= 1e6f) || cfg.anchor == ChainDistribution::kAutoAnchor))
    bad("lobe_anchor must be a number in [0, 1e6] (0: off) or auto", std::to_string(cfg.anchor));
}

void GuidingState::build(const std::vector<SubpathSample>& samples, const Vec3& bmin, const Vec3& bmax,
                         const GuideConfig& cfg) {
  const auto t0 = std::chrono::steady_clock::now();
  const STreeConfig& sc = cfg.stree;
  validate(cfg);
  cfg_ = cfg;
  generation_ = ++g_generation;
  tree_ = STree();
  dists_.clear();
  knn_samples_.clear();
  knn_ = KnnIndex();
  cube_.fit(bmin, bmax);
  if (cfg.structure == GuideStructure::Knn) {
    // Canonical order, so that neighbour ties (broken by index) and the
    // distributions' sums do not depend on the input order.
    std::vector<std::pair<uint64_t, uint32_t>> keys(samples.size());
    for (size_t i = 0; i < samples.size(); ++i) keys[i] = {content_key(samples[i]), uint32_t(i)};
    std::sort(keys.begin(), keys.end(), [&](const auto& a, const auto& b) {
      return canonical_less(a.first, samples[a.second], b.first, samples[b.second]);
    });
    knn_samples_.resize(samples.size());
    std::vector<float> pts(samples.size() * 6);
    for (size_t i = 0; i < samples.size(); ++i) {
      SubpathSample s = samples[keys[i].second];
      s.flags = 0;
      knn_samples_[i] = s;
      for (int a = 0; a < 6; ++a) pts[i * 6 + size_t(a)] = cube_.coord(s, a);
    }
    knn_.build(std::move(pts));
    structure_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    knn_k_ = cfg.knn_k > 0 ? cfg.knn_k
                           : std::max(1, int(std::ceil(sc.c * std::sqrt(double(samples.size())))));
  } else {
    tree_.build(samples, bmin, bmax, sc);
    structure_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    dists_.assign(tree_.num_leaves(), ChainDistribution());
    std::atomic<size_t> next{0};
    auto work = [&] {
      for (size_t i; (i = next.fetch_add(1)) < dists_.size();)
        dists_[i].build(tree_.unfiltered(int(i)), tree_.samples().data(), tree_.filtered(int(i)).data(),
                        tree_.filtered(int(i)).size(), cfg.anchor);
    };
    std::vector<std::thread> pool;
    for (int t = 1; t < std::max(1, sc.threads); ++t) pool.emplace_back(work);
    work();
    for (auto& th : pool) th.join();
  }
  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void GuidingState::knn_neighbours(const Vec3& xD, const Vec3& xL, std::vector<uint32_t>& out) const {
  float q[6];
  cube_.normalise(xD, xL, q);
  knn_.query(q, size_t(knn_k_), out);
}

const ChainDistribution* GuidingState::query(const Vec3& xD, const Vec3& xL) const {
  if (cfg_.structure == GuideStructure::Knn) {
    if (knn_.size() == 0) return nullptr;
    thread_local KnnCache c;
    float q[6];
    cube_.normalise(xD, xL, q);
    if (c.has && c.owner == this && c.generation == generation_ && std::memcmp(q, c.q, sizeof(q)) == 0)
      return &c.dist;
    knn_.query(q, size_t(knn_k_), c.next);
    // the same neighbours as the last query (nearby x_D, the same x_L): reuse
    if (!(c.has && c.owner == this && c.generation == generation_ && c.next == c.idx)) {
      c.idx.swap(c.next);
      c.buf.resize(c.idx.size());
      for (size_t i = 0; i < c.idx.size(); ++i) c.buf[i] = knn_samples_[c.idx[i]];
      c.dist.build(c.buf, cfg_.anchor);
    }
    c.owner = this;
    c.generation = generation_;
    std::memcpy(c.q, q, sizeof(q));
    c.has = true;
    return &c.dist;
  }
  const int l = tree_.leaf_of(xD, xL);
  if (l < 0 || tree_.leaf(l).unfiltered == 0) return nullptr;
  return &dists_[size_t(l)];
}

}  // namespace mpg
