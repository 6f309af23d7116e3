// The seed-chain distribution of one STree leaf (MPG Sec. 5.5, Eqs. 10-12):
// P_e(n) and P_e(tau | n) from the summed sample weights, and per (n, tau) a
// mixture of von Mises-Fisher lobes, one per sample, centred on its omega_D
// with kappa_i = sigma_i^-2, sigma_i the distance to the nearest other sample
// direction of the same (n, tau) (a particle footprint, Hey & Purgathofer 2002).
#pragma once

#include <algorithm>
#include <array>
#include <limits>
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
  // anchor > 0: each lobe is anchored at a point, A_i = x_D,i + omega_D,i *
  // anchor * |x_L,i - x_D,i| (anchor 1: at the distance of the sample's light
  // point), and its centre seen from the query's x_D is normalize(A_i - x_D):
  // the direction from another x_D of the leaf corrected for the parallax of
  // that point (GuideConfig::anchor). 0: the lobe's centre is omega_D,i itself.
  void build(SampleSpan a, const SubpathSample* base = nullptr, const uint32_t* idx = nullptr, size_t nidx = 0,
             float anchor = 0.f);
  void build(const std::vector<SubpathSample>& samples, float anchor = 0.f) {
    build(SampleSpan{samples.data(), samples.size()}, nullptr, nullptr, 0, anchor);
  }
  // anchor < 0 (kAutoAnchor): each leaf picks its anchor among 0 (off), 0.1,
  // 0.3, 1 and 3, the one whose lobes are tightest seen from the samples'
  // mean x_D (chain_distribution.cpp).
  static constexpr float kAutoAnchor = -1.f;
  bool anchored() const { return anchor_ > 0.f; }
  float anchor() const { return anchor_; }   // the anchor the leaf uses (0: off)
  bool empty() const { return n_dist_.empty(); }

  int sample_n(float u) const;
  // P_e(n), read from a copy kept in the object (no second cache line to
  // fetch: the estimator reads it for every estimate).
  float pmf_n(int n) const { return n < 1 || n > kMaxN ? 0.f : n_pmf_[size_t(n - 1)]; }
  // sum_{k=1..nmax} P_e(k), summed in double in the order k = 1, 2, ... (as a
  // loop over pmf_n would: the same bits).
  double mass_n(int nmax) const { return n_mass_[size_t(std::clamp(nmax, 0, kMaxN))]; }
  float pmf_tau(int n, uint16_t tau) const;
  // Direction for (n, tau) at the query's x_D (which anchored lobes aim
  // from; unanchored ones ignore it); density is per solid angle.
  // (kappa_cap: each lobe's kappa capped there, pdf_dir_defensive's broad share)
  bool sample_dir(int n, uint16_t tau, double u_lobe, const Vec2& u, const Vec3& xD, Vec3& dir,
                  float kappa_cap = std::numeric_limits<float>::infinity()) const;
  float pdf_dir(int n, uint16_t tau, const Vec3& xD, const Vec3& dir) const;
  // The guided trace's direction density with a defensive share: (1 - beta)
  // pdf_dir + beta times the same mixture with every lobe's kappa capped at
  // kappa_cap (design-notes "The guided trace's defensive lobes"), which
  // sample_dir_of(..., kappa_cap) draws. pdf_dir is this at beta 0, no cap.
  double pdf_dir_defensive(int n, uint16_t tau, const Vec3& xD, const Vec3& dir, double beta,
                           float kappa_cap) const;
  // The lobes pdf_dir visits for (n, tau): its cost (one dot product each)
  uint32_t lobe_count(int n, uint16_t tau) const {
    const int t = find_type(n, tau);
    return t < 0 ? 0u : types_[size_t(t)].count;
  }
  // The draws the estimator makes, by the index of a type (n, tau) in the
  // leaf's table: sample_type draws tau ~ P_e(tau | n) (-1: no sample of
  // length n), sample_dir_of the direction sample_dir gives for that type,
  // without looking the type up again.
  int sample_type(int n, float u) const;
  // Does the leaf hold a sample of type (n, tau)?
  bool has_type(int n, uint16_t tau) const { return find_type(n, tau) >= 0; }
  uint16_t type_tau(int t) const { return types_[size_t(t)].tau; }
  // Bytes of the leaf's distribution: the object and its tables' heap.
  size_t memory_bytes() const {
    return sizeof(*this) + n_dist_.memory_bytes() + types_.capacity() * sizeof(Type) +
           lobes_.capacity() * sizeof(LobeEntry) + lobe_pmf_.capacity() * sizeof(float);
  }
  // (kappa_cap: the lobe's kappa capped there, pdf_dir_defensive's broad share)
  bool sample_dir_of(int t, double u_lobe, const Vec2& u, const Vec3& xD, Vec3& dir,
                     float kappa_cap = std::numeric_limits<float>::infinity()) const;

  // What sample_dir reads of lobe i, in one 24-byte record: its vMF and its
  // bin of an alias table over the lobe weights (Walker 1977, Vose 1991):
  // bin i keeps lobe i with probability q, else gives `alias`. A draw reads
  // one or two records where the CDF's guide table and binary search, then
  // mu and kappa, missed the cache up to four times (pool: design-notes).
  struct LobeEntry {
    Vec3 mu;   // the lobe's centre, or its anchor point A_i when anchored()
    float kappa;
    float q;
    uint32_t alias;
  };

 private:
  // One type (n, tau) of the leaf. The types sit in (n, tau) order, those of
  // length n in [type_begin_[n - 1], type_begin_[n]); a draw of tau scans
  // them by cdf (as DiscreteDistribution::sample does, the same index), then
  // reads the type's alias records in lobes_: two arrays for the whole draw,
  // where per-n vectors and a map of (n, tau) took up to seven dependent
  // loads (design-notes, "Manifold path guiding": the lobe draw).
  struct Type {
    double cdf;        // P_e(tau' <= tau | n): the upper end of its bin
    float pmf;         // P_e(tau | n) (Eq. 11)
    uint16_t tau;
    uint32_t first, count;  // its lobes: lobes_[first, first + count)
  };
  int find_type(int n, uint16_t tau) const;
  // The centre of lobe e seen from xD: sampling and density call this one
  // function, so both see the same bits. An anchor at xD itself (a measure-
  // zero case) gives +z.
  Vec3 centre(const LobeEntry& e, const Vec3& xD) const {
    if (!(anchor_ > 0.f)) return e.mu;
    const Vec3 d = e.mu - xD;
    const float l2 = glm::dot(d, d);
    return l2 > 1e-24f && std::isfinite(l2) ? d / std::sqrt(l2) : Vec3(0.f, 0.f, 1.f);
  }

  DiscreteDistribution n_dist_;                    // index n - 1
  std::array<float, kMaxN> n_pmf_{};               // its pmf
  std::array<double, kMaxN + 1> n_mass_{};         // its running sums from n = 1 (mass_n)
  std::array<uint32_t, kMaxN + 1> type_begin_{};
  std::vector<Type> types_;
  std::vector<LobeEntry> lobes_;                   // every type's lobes with their alias bins
  std::vector<float> lobe_pmf_;                    // their mixture weights within the type (pdf_dir)
  float anchor_ = 0.f;   // the anchor its lobes use (0: unanchored)
};

}  // namespace mpg
