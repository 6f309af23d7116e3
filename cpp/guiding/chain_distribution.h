// The seed-chain distribution of one STree leaf (MPG Sec. 5.5, Eqs. 10-12):
// P_e(n) and P_e(tau | n) from the summed sample weights, and per (n, tau) a
// mixture of von Mises-Fisher lobes, one per sample, centred on its omega_D
// with kappa_i = sigma_i^-2, sigma_i the distance to the nearest other sample
// direction of the same (n, tau) (a particle footprint, Hey & Purgathofer 2002).
#pragma once

#include <map>
#include <vector>

#include "core/distribution.h"
#include "guiding/subpath_sample.h"

namespace mpg {

class ChainDistribution {
 public:
  static constexpr int kMaxN = 16;
  static constexpr float kMaxKappa = 1e8f;
  static constexpr float kSingleKappa = 100.f;  // a lone sample's lobe (sigma = 0.1)

  // From the samples of `a` then base[idx[0]], ..., base[idx[nidx - 1]] (a
  // leaf's unfiltered samples and its filtered copies); the result depends on
  // their order only through floating-point rounding of the sums, so callers
  // pass a canonical order.
  void build(SampleSpan a, const SubpathSample* base = nullptr, const uint32_t* idx = nullptr, size_t nidx = 0);
  void build(const std::vector<SubpathSample>& samples) { build(SampleSpan{samples.data(), samples.size()}); }
  bool empty() const { return n_dist_.empty(); }

  int sample_n(float u) const;
  float pmf_n(int n) const;
  // Type for a given n: returns false when there is no sample of length n.
  bool sample_tau(int n, float u, uint16_t& tau) const;
  float pmf_tau(int n, uint16_t tau) const;
  // Direction for (n, tau); density is per solid angle.
  bool sample_dir(int n, uint16_t tau, double u_lobe, const Vec2& u, Vec3& dir) const;
  float pdf_dir(int n, uint16_t tau, const Vec3& dir) const;

  // What sample_dir reads of lobe i, in one 24-byte record: its vMF and its
  // bin of an alias table over the lobe weights (Walker 1977, Vose 1991):
  // bin i keeps lobe i with probability q, else gives `alias`. A draw reads
  // one or two records where the CDF's guide table and binary search, then
  // mu and kappa, missed the cache up to four times (pool: design-notes).
  struct LobeEntry {
    Vec3 mu;
    float kappa;
    float q;
    uint32_t alias;
  };
  struct Lobes {
    DiscreteDistribution dist;       // the mixture weights (pdf_dir)
    std::vector<LobeEntry> entries;  // the lobes, with their alias-table bins (sample_dir)
  };
  const Lobes* lobes(int n, uint16_t tau) const;

 private:
  DiscreteDistribution n_dist_;                    // index n - 1
  std::vector<std::vector<uint16_t>> tau_keys_;    // per n
  std::vector<DiscreteDistribution> tau_dist_;     // per n
  std::map<std::pair<int, uint16_t>, Lobes> lobes_;
};

}  // namespace mpg
