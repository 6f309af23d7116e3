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
static void build_alias(ChainDistribution::Lobes& L, const std::vector<Vec3>& mu,
                        const std::vector<float>& kappa) {
  const size_t m = mu.size();
  L.entries.clear();
  if (m == 0 || L.dist.empty()) return;
  L.entries.resize(m);
  std::vector<double> p(m);
  std::vector<uint32_t> small, large;
  for (size_t i = 0; i < m; ++i) {
    L.entries[i] = {mu[i], kappa[i], 1.f, uint32_t(i)};
    p[i] = double(L.dist.pmf(i)) * double(m);
    (p[i] < 1.0 ? small : large).push_back(uint32_t(i));
  }
  size_t si = 0, li = 0;
  while (si < small.size() && li < large.size()) {
    const uint32_t s = small[si++], l = large[li];
    L.entries[s].q = float(p[s]);
    L.entries[s].alias = l;
    p[l] -= 1.0 - p[s];
    if (p[l] < 1.0) {  // the large one is small now
      ++li;
      small.push_back(l);
    }
  }
  // What is left holds (up to rounding) exactly its own mass: q = 1.
}

void ChainDistribution::build(SampleSpan a, const SubpathSample* base, const uint32_t* idx, size_t nidx) {
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
  // groups in (n, tau) order
  thread_local std::vector<uint32_t> rank;
  rank.resize(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) rank[g] = uint32_t(g);
  std::sort(rank.begin(), rank.end(), [&](uint32_t x, uint32_t y) { return groups[x].key < groups[y].key; });
  tau_keys_.assign(kMaxN, {});
  tau_dist_.assign(kMaxN, DiscreteDistribution());
  {
    std::vector<float> w;
    for (size_t r = 0; r < rank.size();) {
      const uint32_t n = groups[rank[r]].key >> 16;
      w.clear();
      for (; r < rank.size() && (groups[rank[r]].key >> 16) == n; ++r) {
        tau_keys_[n].push_back(uint16_t(groups[rank[r]].key & 0xffffu));
        w.push_back(groups[rank[r]].weight);
      }
      tau_dist_[n].build(w);
    }
  }
  // one vMF lobe per sample (Eq. 12), per (n, tau)
  lobes_.clear();
  struct Scratch { std::vector<Vec3> mu; std::vector<float> kappa, weight; };
  std::vector<Scratch> lobes(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) {
    lobes[g].mu.reserve(groups[g].count);
    lobes[g].weight.reserve(groups[g].count);
  }
  for (size_t i = 0; i < acc.size(); ++i) {
    Scratch& S = lobes[gid[i]];
    S.mu.push_back(oct_decode(Vec2(acc[i]->dir[0], acc[i]->dir[1])));
    S.weight.push_back(acc[i]->weight);
  }
  for (size_t g = 0; g < groups.size(); ++g) {
    Scratch& S = lobes[g];
    const size_t m = S.mu.size();
    S.kappa.resize(m);
    nearest_distances(S.mu.data(), m, S.kappa.data());  // sigma_i
    for (size_t i = 0; i < m; ++i) {
      // Eq. 12: kappa_i = sigma_i^-2 (capped; a lone sample gets a broad lobe)
      const float sg = S.kappa[i];
      S.kappa[i] = std::isinf(sg) ? kSingleKappa : std::min(kMaxKappa, 1.f / std::max(sg * sg, 1e-30f));
    }
    Lobes L;
    L.dist.build(S.weight);
    build_alias(L, S.mu, S.kappa);
    lobes_.emplace(std::make_pair(int(groups[g].key >> 16) + 1, uint16_t(groups[g].key & 0xffffu)), std::move(L));
  }
}

int ChainDistribution::sample_n(float u) const { return int(n_dist_.sample(u)) + 1; }
float ChainDistribution::pmf_n(int n) const { return n < 1 || n > kMaxN ? 0.f : n_dist_.pmf(size_t(n - 1)); }

bool ChainDistribution::sample_tau(int n, float u, uint16_t& tau) const {
  if (n < 1 || n > kMaxN || tau_dist_[size_t(n - 1)].empty()) return false;
  tau = tau_keys_[size_t(n - 1)][tau_dist_[size_t(n - 1)].sample(u)];
  return true;
}

float ChainDistribution::pmf_tau(int n, uint16_t tau) const {
  if (n < 1 || n > kMaxN) return 0.f;
  const auto& k = tau_keys_[size_t(n - 1)];
  for (size_t i = 0; i < k.size(); ++i)
    if (k[i] == tau) return tau_dist_[size_t(n - 1)].pmf(i);
  return 0.f;
}

const ChainDistribution::Lobes* ChainDistribution::lobes(int n, uint16_t tau) const {
  auto it = lobes_.find({n, tau});
  return it == lobes_.end() ? nullptr : &it->second;
}

bool ChainDistribution::sample_dir(int n, uint16_t tau, double u_lobe, const Vec2& u, Vec3& dir) const {
  const Lobes* L = lobes(n, tau);
  if (!L || L->entries.empty()) return false;
  // the alias table's bin from u_lobe, and the fraction within it for q
  const size_t m = L->entries.size();
  const double x = u_lobe * double(m);  // a double: the fraction keeps its bits for large m
  const size_t b = std::min(size_t(x), m - 1);
  const LobeEntry* e = &L->entries[b];
  if (!(x - double(b) < double(e->q))) e = &L->entries[e->alias];
  const Vec3 local = warp::square_to_vmf(u, e->kappa);
  dir = Frame(e->mu).to_world(local);
  return true;
}

float ChainDistribution::pdf_dir(int n, uint16_t tau, const Vec3& dir) const {
  const Lobes* L = lobes(n, tau);
  if (!L || L->dist.empty()) return 0.f;
  double p = 0.0;
  for (size_t i = 0; i < L->entries.size(); ++i)
    p += double(L->dist.pmf(i)) *
         warp::vmf_pdf_cos(double(glm::dot(L->entries[i].mu, dir)), double(L->entries[i].kappa));
  return float(p);
}

}  // namespace mpg
