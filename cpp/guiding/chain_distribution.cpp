#include "guiding/chain_distribution.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "core/warp.h"

namespace mpg {

namespace {
// Exact distance from each direction to its nearest other one (chordal,
// Eq. 12's sigma_i): directions sorted along the axis of largest spread, and
// each scans both ways until the gap along that axis alone exceeds the best
// distance found. Bounded by the neighbours within sigma_i along one axis
// (O(m log m) for spread-out or clustered directions; exact in every case).
void nearest_distances(const Vec3* d, size_t m, float* best) {
  for (size_t i = 0; i < m; ++i) best[i] = kInf;
  if (m < 2) return;
  Vec3 lo(kInf), hi(-kInf);
  for (size_t i = 0; i < m; ++i) {
    lo = glm::min(lo, d[i]);
    hi = glm::max(hi, d[i]);
  }
  const Vec3 ext = hi - lo;
  const int ax = ext.x >= ext.y && ext.x >= ext.z ? 0 : (ext.y >= ext.z ? 1 : 2);
  // sort by the coordinate along ax: (order-preserving bits of the float,
  // index) packed in one integer
  thread_local std::vector<uint64_t> order;
  thread_local std::vector<Vec3> p;  // sorted copy: the scans read memory in order
  thread_local std::vector<float> key;
  order.resize(m);
  p.resize(m);
  key.resize(m);
  for (size_t i = 0; i < m; ++i) {
    uint32_t u;
    const float f = d[i][ax] + 0.f;  // -0 -> +0
    std::memcpy(&u, &f, 4);
    u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    order[i] = uint64_t(u) << 32 | uint32_t(i);
  }
  std::sort(order.begin(), order.end());
  for (size_t o = 0; o < m; ++o) {
    p[o] = d[uint32_t(order[o])];
    key[o] = p[o][ax];
  }
  for (size_t o = 0; o < m; ++o) {
    float b2 = kInf;  // squared best distance
    const Vec3 q = p[o];
    const float k = key[o];
    for (size_t j = o + 1; j < m; ++j) {
      const float g = key[j] - k;
      if (g * g >= b2) break;
      const Vec3 t = p[j] - q;
      b2 = std::min(b2, glm::dot(t, t));
    }
    for (size_t j = o; j-- > 0;) {
      const float g = k - key[j];
      if (g * g >= b2) break;
      const Vec3 t = p[j] - q;
      b2 = std::min(b2, glm::dot(t, t));
    }
    best[uint32_t(order[o])] = std::sqrt(b2);
  }
}
}  // namespace

// Vose's alias method over the lobes' pmf (as DiscreteDistribution normalised
// it): m bins of mass 1/m, each split between its own lobe (q) and one alias.
// Small and large bins are paired in index order, so the table is a
// function of the weights alone. Zero-weight lobes get q = 0 and are never
// drawn unless every lobe has zero weight (then dist is empty and so is this).
static void build_alias(const DiscreteDistribution& dist, const std::vector<Vec3>& mu,
                        const std::vector<float>& kappa, ChainDistribution::LobeEntry* out) {
  const size_t m = mu.size();
  std::vector<double> p(m);
  std::vector<uint32_t> small, large;
  for (size_t i = 0; i < m; ++i) {
    out[i] = {mu[i], kappa[i], 1.f, uint32_t(i)};
    p[i] = double(dist.pmf(i)) * double(m);
    (p[i] < 1.0 ? small : large).push_back(uint32_t(i));
  }
  size_t si = 0, li = 0;
  while (si < small.size() && li < large.size()) {
    const uint32_t s = small[si++], l = large[li];
    out[s].q = float(p[s]);
    out[s].alias = l;
    p[l] -= 1.0 - p[s];
    if (p[l] < 1.0) {  // the large one is small now
      ++li;
      small.push_back(l);
    }
  }
  // What is left holds (up to rounding) exactly its own mass: q = 1.
}

void ChainDistribution::build(SampleSpan a, const SubpathSample* base, const uint32_t* idx, size_t nidx,
                              float anchor) {
  // Group the samples by (n, tau) in their given order: a small flat table of
  // group keys (a leaf rarely has more than a few dozen types).
  struct Group { uint32_t key; uint32_t count = 0; float weight = 0.f; };
  thread_local std::vector<Group> groups;
  thread_local std::vector<uint32_t> gid;                 // per accepted sample
  thread_local std::vector<const SubpathSample*> acc;     // accepted samples
  groups.clear();
  gid.clear();
  acc.clear();
  std::vector<float> wn(kMaxN, 0.f);
  uint32_t last = ~0u;
  auto add = [&](const SubpathSample& s) {
    if (s.n < 1 || s.n > kMaxN || !(s.weight > 0.f) || !std::isfinite(s.weight)) return;
    const uint32_t key = uint32_t(s.n - 1) << 16 | s.tau;
    if (last >= groups.size() || groups[last].key != key) {
      last = 0;
      while (last < groups.size() && groups[last].key != key) ++last;
      if (last == groups.size()) groups.push_back(Group{key});
    }
    wn[size_t(s.n - 1)] += s.weight;   // Eq. 10
    groups[last].weight += s.weight;   // Eq. 11
    groups[last].count++;
    gid.push_back(last);
    acc.push_back(&s);
  };
  for (const SubpathSample& s : a) add(s);
  for (size_t i = 0; i < nidx; ++i) {
    if (i + 16 < nidx) __builtin_prefetch(base + idx[i + 16]);
    add(base[idx[i]]);
  }
  n_dist_.build(wn);
  n_mass_[0] = 0.0;
  for (int k = 1; k <= kMaxN; ++k) {
    n_pmf_[size_t(k - 1)] = n_dist_.pmf(size_t(k - 1));
    n_mass_[size_t(k)] = n_mass_[size_t(k - 1)] + double(n_pmf_[size_t(k - 1)]);
  }
  // groups in (n, tau) order
  thread_local std::vector<uint32_t> rank;
  rank.resize(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) rank[g] = uint32_t(g);
  std::sort(rank.begin(), rank.end(), [&](uint32_t x, uint32_t y) { return groups[x].key < groups[y].key; });
  // P_e(tau | n) per n (Eq. 11), through DiscreteDistribution so that the
  // table holds its normalised cdf and pmf bit for bit.
  types_.clear();
  types_.reserve(rank.size());
  type_begin_.fill(0);
  thread_local std::vector<uint32_t> type_group;  // the group of each type
  type_group.clear();
  {
    std::vector<float> w;
    DiscreteDistribution d;
    uint32_t n_done = 0;  // lengths below this have their begin set
    for (size_t r = 0; r < rank.size();) {
      const uint32_t n = groups[rank[r]].key >> 16;  // n - 1
      for (; n_done <= n; ++n_done) type_begin_[n_done] = uint32_t(types_.size());
      w.clear();
      const size_t r0 = r;
      for (; r < rank.size() && (groups[rank[r]].key >> 16) == n; ++r) w.push_back(groups[rank[r]].weight);
      d.build(w);
      if (d.empty()) continue;  // (weights are > 0: not reached) no draw at this n
      for (size_t i = 0; i < w.size(); ++i) {
        types_.push_back(Type{d.cdf_upper(i), d.pmf(i), uint16_t(groups[rank[r0 + i]].key & 0xffffu), 0u, 0u});
        type_group.push_back(rank[r0 + i]);
      }
    }
    for (; n_done <= uint32_t(kMaxN); ++n_done) type_begin_[n_done] = uint32_t(types_.size());
  }
  // one vMF lobe per sample (Eq. 12), per (n, tau)
  struct Scratch { std::vector<Vec3> mu; std::vector<float> kappa, weight; };
  std::vector<Scratch> lobes(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) {
    lobes[g].mu.reserve(groups[g].count);
    lobes[g].weight.reserve(groups[g].count);
  }
  // Anchored lobes: the anchors, and the directions to them from the
  // samples' mean x_D, from which the footprints sigma_i are measured
  // (the leaf's parallax taken out, as the query sees them). fill(a) sets
  // both for anchor a (0: the directions themselves).
  std::vector<std::vector<Vec3>> anchors(groups.size());
  Vec3 centroid(0.f);
  if (anchor != 0.f && !acc.empty()) {
    glm::dvec3 sum(0.0);
    for (const SubpathSample* s : acc) sum += glm::dvec3(s->pD());
    centroid = Vec3(sum / double(acc.size()));
  }
  auto fill = [&](float a) {
    for (size_t g = 0; g < groups.size(); ++g) {
      lobes[g].mu.clear();
      lobes[g].weight.clear();
      anchors[g].clear();
    }
    for (size_t i = 0; i < acc.size(); ++i) {
      Scratch& S = lobes[gid[i]];
      const Vec3 mu = oct_decode(Vec2(acc[i]->dir[0], acc[i]->dir[1]));
      if (a > 0.f) {
        const Vec3 pd = acc[i]->pD();
        const Vec3 A = pd + mu * (a * glm::length(acc[i]->pL() - pd));
        anchors[gid[i]].push_back(A);
        const Vec3 d = A - centroid;
        const float l2 = glm::dot(d, d);
        S.mu.push_back(l2 > 1e-24f && std::isfinite(l2) ? d / std::sqrt(l2) : mu);
      } else {
        S.mu.push_back(mu);
      }
      S.weight.push_back(acc[i]->weight);
    }
  };
  float a_used = anchor;
  if (anchor < 0.f) {
    // kAutoAnchor: per leaf the candidate whose lobes are tightest seen from
    // the leaf's mean x_D, by the mean log sigma_i over its samples (a
    // leave-one-out likelihood of each direction under its nearest
    // neighbour's lobe, -2 log sigma + const): the parallax that lines the
    // samples' directions up. Ties keep the unanchored lobes.
    static constexpr float kCandidates[] = {0.f, 0.1f, 0.3f, 1.f, 3.f};
    double best = kInf;
    a_used = 0.f;
    std::vector<float> sg;
    for (float a : kCandidates) {
      fill(a);
      double sum = 0.0;
      size_t cnt = 0;
      for (size_t g = 0; g < groups.size(); ++g) {
        const size_t m = lobes[g].mu.size();
        sg.resize(m);
        nearest_distances(lobes[g].mu.data(), m, sg.data());
        for (size_t i = 0; i < m; ++i)
          if (std::isfinite(sg[i])) {
            sum += std::log(double(std::max(sg[i], 1e-4f)));   // (kMaxKappa's floor on sigma)
            ++cnt;
          }
      }
      if (cnt == 0) break;   // lone samples only: nothing to line up
      const double score = sum / double(cnt);
      if (score < best) {
        best = score;
        a_used = a;
      }
    }
  }
  anchor_ = a_used;
  fill(a_used);
  lobes_.clear();
  lobe_pmf_.clear();
  lobes_.reserve(acc.size());
  lobe_pmf_.reserve(acc.size());
  for (size_t ti = 0; ti < types_.size(); ++ti) {
    Type& t = types_[ti];
    Scratch& S = lobes[type_group[ti]];
    const size_t m = S.mu.size();
    S.kappa.resize(m);
    nearest_distances(S.mu.data(), m, S.kappa.data());  // sigma_i
    for (size_t i = 0; i < m; ++i) {
      // Eq. 12: kappa_i = sigma_i^-2 (capped; a lone sample gets a broad lobe)
      const float sg = S.kappa[i];
      S.kappa[i] = std::isinf(sg) ? kSingleKappa : std::min(kMaxKappa, 1.f / std::max(sg * sg, 1e-30f));
    }
    DiscreteDistribution dist(S.weight);
    t.first = uint32_t(lobes_.size());
    if (m == 0 || dist.empty()) continue;  // (not reached: weights are > 0) count 0, never drawn
    t.count = uint32_t(m);
    lobes_.resize(lobes_.size() + m);
    build_alias(dist, anchored() ? anchors[type_group[ti]] : S.mu, S.kappa, lobes_.data() + t.first);
    for (size_t i = 0; i < m; ++i) lobe_pmf_.push_back(dist.pmf(i));
  }
}

int ChainDistribution::sample_n(float u) const { return int(n_dist_.sample(u)) + 1; }

int ChainDistribution::sample_type(int n, float u) const {
  if (n < 1 || n > kMaxN) return -1;
  const uint32_t b = type_begin_[size_t(n - 1)], e = type_begin_[size_t(n)];
  if (b == e) return -1;
  // DiscreteDistribution::sample's choice: the first bin whose cdf exceeds u,
  // then past bins of zero probability
  const double x = u;
  uint32_t i = b;
  while (i + 1 < e && !(x < types_[i].cdf)) ++i;
  while (types_[i].pmf == 0.f && i + 1 < e) ++i;
  return int(i);
}

int ChainDistribution::find_type(int n, uint16_t tau) const {
  if (n < 1 || n > kMaxN) return -1;
  for (uint32_t i = type_begin_[size_t(n - 1)]; i < type_begin_[size_t(n)]; ++i)
    if (types_[i].tau == tau) return int(i);
  return -1;
}

float ChainDistribution::pmf_tau(int n, uint16_t tau) const {
  const int t = find_type(n, tau);
  return t < 0 ? 0.f : types_[size_t(t)].pmf;
}

bool ChainDistribution::sample_dir_of(int t, double u_lobe, const Vec2& u, const Vec3& xD, Vec3& dir,
                                      float kappa_cap) const {
  const Type& ty = types_[size_t(t)];
  if (ty.count == 0) return false;
  // the alias table's bin from u_lobe, and the fraction within it for q
  const LobeEntry* L = lobes_.data() + ty.first;
  const size_t m = ty.count;
  const double x = u_lobe * double(m);  // a double: the fraction keeps its bits for large m
  const size_t b = std::min(size_t(x), m - 1);
  const LobeEntry* e = &L[b];
  if (!(x - double(b) < double(e->q))) e = &L[e->alias];
  const Vec3 local = warp::square_to_vmf(u, std::min(e->kappa, kappa_cap));
  dir = Frame(centre(*e, xD)).to_world(local);
  return true;
}

bool ChainDistribution::sample_dir(int n, uint16_t tau, double u_lobe, const Vec2& u, const Vec3& xD,
                                   Vec3& dir, float kappa_cap) const {
  const int t = find_type(n, tau);
  return t >= 0 && sample_dir_of(t, u_lobe, u, xD, dir, kappa_cap);
}

float ChainDistribution::pdf_dir(int n, uint16_t tau, const Vec3& xD, const Vec3& dir) const {
  // (no cap: every lobe takes the loop's uncapped branch, the sum is its p)
  return float(pdf_dir_defensive(n, tau, xD, dir, 0.0, std::numeric_limits<float>::infinity()));
}

double ChainDistribution::pdf_dir_defensive(int n, uint16_t tau, const Vec3& xD, const Vec3& dir, double beta,
                                            float kappa_cap) const {
  const int t = find_type(n, tau);
  if (t < 0) return 0.0;
  const Type& ty = types_[size_t(t)];
  double p = 0.0, pd = 0.0;
  const double cap = double(kappa_cap);
  const double norm_cap = warp::vmf_norm(cap);   // (cap >= 1e-3: the callers check it; inf for pdf_dir, unused)
  for (uint32_t i = ty.first; i < ty.first + ty.count; ++i) {
    // A term below e^-40 of its lobe's peak is left out (the guided trace
    // evaluates this for every path it shares, over all of a leaf's lobes;
    // the skip makes most of them a dot product); per kappa, and the capped
    // kappa is the smaller, so past its bound both terms are.
    const double c = double(glm::dot(centre(lobes_[i], xD), dir));
    const double k = double(lobes_[i].kappa);
    if (!(k > cap)) {
      // (a lobe at or below the cap: both terms are its own vMF)
      if (k * (1.0 - std::min(c, 1.0)) > 40.0) continue;
      const double t = double(lobe_pmf_[i]) * warp::vmf_pdf_cos(c, k);
      p += t;
      pd += t;
      continue;
    }
    const double one_minus = 1.0 - std::min(c, 1.0);
    if (cap * one_minus > 40.0) continue;
    const double w = double(lobe_pmf_[i]);
    // (vmf_pdf_cos's terms, its normalisation of the cap computed once)
    if (k * one_minus <= 40.0) p += w * warp::vmf_norm(k) * std::exp(-k * one_minus);
    pd += w * norm_cap * std::exp(-cap * one_minus);
  }
  return (1.0 - beta) * p + beta * pd;
}

}  // namespace mpg
