#include "guiding/chain_distribution.h"

#include <algorithm>
#include <cmath>

#include "core/warp.h"

namespace mpg {

namespace {
// Distance from each direction to its nearest other one (chordal), by a sweep
// over directions sorted along x: O(m log m) plus the window checks.
std::vector<float> nearest_distances(const std::vector<Vec3>& d) {
  const size_t m = d.size();
  std::vector<float> best(m, kInf);
  std::vector<size_t> order(m);
  for (size_t i = 0; i < m; ++i) order[i] = i;
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return d[a].x < d[b].x; });
  for (size_t oi = 0; oi < m; ++oi) {
    const size_t i = order[oi];
    for (size_t oj = oi + 1; oj < m; ++oj) {
      const size_t j = order[oj];
      const float dx = d[j].x - d[i].x;
      if (dx >= best[i] && dx >= best[j]) break;
      const float dist = glm::length(d[i] - d[j]);
      best[i] = std::min(best[i], dist);
      best[j] = std::min(best[j], dist);
    }
  }
  return best;
}
}  // namespace

void ChainDistribution::build(const std::vector<SubpathSample>& samples) {
  std::vector<float> wn(kMaxN, 0.f);
  std::vector<std::map<uint16_t, float>> wt(kMaxN);
  std::map<std::pair<int, uint16_t>, std::pair<std::vector<Vec3>, std::vector<float>>> groups;
  for (const SubpathSample& s : samples) {
    if (s.n < 1 || s.n > kMaxN || !(s.weight > 0.f) || !std::isfinite(s.weight)) continue;
    wn[size_t(s.n - 1)] += s.weight;                    // Eq. 10
    wt[size_t(s.n - 1)][s.tau] += s.weight;             // Eq. 11
    auto& g = groups[{int(s.n), s.tau}];
    g.first.push_back(oct_decode(Vec2(s.dir[0], s.dir[1])));
    g.second.push_back(s.weight);
  }
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
