#include "guiding/chain_distribution.h"

#include <algorithm>
#include <cmath>

#include "core/warp.h"

namespace mpg {

namespace {
// Exact distance from each direction to its nearest other one (chordal,
// Eq. 12's sigma_i): directions sorted along the axis of largest spread, and
// each scans both ways until the gap along that axis alone exceeds the best
// distance found. Bounded by the neighbours within sigma_i along one axis
// (O(m log m) for spread-out or clustered directions; exact in every case).
std::vector<float> nearest_distances(const std::vector<Vec3>& d) {
  const size_t m = d.size();
  std::vector<float> best(m, kInf);
  if (m < 2) return best;
  Vec3 lo(kInf), hi(-kInf);
  for (const Vec3& v : d) {
    lo = glm::min(lo, v);
    hi = glm::max(hi, v);
  }
  const Vec3 ext = hi - lo;
  const int ax = ext.x >= ext.y && ext.x >= ext.z ? 0 : (ext.y >= ext.z ? 1 : 2);
  struct Item { float key; uint32_t i; };
  std::vector<Item> order(m);
  for (size_t i = 0; i < m; ++i) order[i] = {d[i][ax], uint32_t(i)};
  std::sort(order.begin(), order.end(), [](const Item& a, const Item& b) {
    return a.key < b.key || (a.key == b.key && a.i < b.i);
  });
  std::vector<Vec3> p(m);  // sorted copy: the scans read memory in order
  for (size_t o = 0; o < m; ++o) p[o] = d[order[o].i];
  for (size_t o = 0; o < m; ++o) {
    float b2 = kInf;  // squared best distance
    const Vec3 q = p[o];
    const float k = order[o].key;
    for (size_t j = o + 1; j < m; ++j) {
      const float g = order[j].key - k;
      if (g * g >= b2) break;
      const Vec3 t = p[j] - q;
      b2 = std::min(b2, glm::dot(t, t));
    }
    for (size_t j = o; j-- > 0;) {
      const float g = k - order[j].key;
      if (g * g >= b2) break;
      const Vec3 t = p[j] - q;
      b2 = std::min(b2, glm::dot(t, t));
    }
    best[order[o].i] = std::sqrt(b2);
  }
  return best;
}
}  // namespace

void ChainDistribution::build(SampleSpan a, SampleSpan b) {
  std::vector<float> wn(kMaxN, 0.f);
  std::vector<std::map<uint16_t, float>> wt(kMaxN);
  std::map<std::pair<int, uint16_t>, std::pair<std::vector<Vec3>, std::vector<float>>> groups;
  auto add = [&](const SubpathSample& s) {
    if (s.n < 1 || s.n > kMaxN || !(s.weight > 0.f) || !std::isfinite(s.weight)) return;
    wn[size_t(s.n - 1)] += s.weight;                    // Eq. 10
    wt[size_t(s.n - 1)][s.tau] += s.weight;             // Eq. 11
    auto& g = groups[{int(s.n), s.tau}];
    g.first.push_back(oct_decode(Vec2(s.dir[0], s.dir[1])));
    g.second.push_back(s.weight);
  };
  for (const SubpathSample& s : a) add(s);
  for (const SubpathSample& s : b) add(s);
  n_dist_.build(wn);
  tau_keys_.assign(kMaxN, {});
  tau_dist_.assign(kMaxN, DiscreteDistribution());
  for (int n = 0; n < kMaxN; ++n) {
    std::vector<float> w;
    for (const auto& kv : wt[size_t(n)]) {
      tau_keys_[size_t(n)].push_back(kv.first);
      w.push_back(kv.second);
    }
    tau_dist_[size_t(n)].build(w);
  }
  lobes_.clear();
  for (auto& kv : groups) {
    Lobes L;
    L.mu = std::move(kv.second.first);
    L.weight = std::move(kv.second.second);
    const std::vector<float> sigma = nearest_distances(L.mu);
    L.kappa.resize(L.mu.size());
    for (size_t i = 0; i < L.mu.size(); ++i) {
      // Eq. 12: kappa_i = sigma_i^-2 (capped; a lone sample gets a broad lobe)
      L.kappa[i] = std::isinf(sigma[i]) ? kSingleKappa
                                        : std::min(kMaxKappa, 1.f / std::max(sigma[i] * sigma[i], 1e-30f));
    }
    L.dist.build(L.weight);
    lobes_.emplace(kv.first, std::move(L));
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

bool ChainDistribution::sample_dir(int n, uint16_t tau, float u_lobe, const Vec2& u, Vec3& dir) const {
  const Lobes* L = lobes(n, tau);
  if (!L || L->dist.empty()) return false;
  const size_t i = L->dist.sample(u_lobe);
  const Vec3 local = warp::square_to_vmf(u, L->kappa[i]);
  dir = Frame(L->mu[i]).to_world(local);
  return true;
}

float ChainDistribution::pdf_dir(int n, uint16_t tau, const Vec3& dir) const {
  const Lobes* L = lobes(n, tau);
  if (!L || L->dist.empty()) return 0.f;
  double p = 0.0;
  for (size_t i = 0; i < L->mu.size(); ++i)
    p += double(L->dist.pmf(i)) * warp::vmf_pdf_cos(double(glm::dot(L->mu[i], dir)), double(L->kappa[i]));
  return float(p);
}

}  // namespace mpg
