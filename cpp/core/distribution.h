// Discrete 1D distribution and a piecewise-constant 2D distribution (for
// environment maps), each with sample and pmf/pdf.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#include "core/math.h"

namespace mpg {

class DiscreteDistribution {
 public:
  DiscreteDistribution() = default;
  explicit DiscreteDistribution(const std::vector<float>& weights) { build(weights); }

  // Heap bytes of its tables (capacity, not size: what the guide's memory holds).
  size_t memory_bytes() const {
    return pmf_.capacity() * sizeof(float) + cdf_.capacity() * sizeof(double) + guide_.capacity() * sizeof(guide_[0]);
  }
  void build(const std::vector<float>& weights) {
    pmf_.assign(weights.size(), 0.f);
    cdf_.assign(weights.size() + 1, 0.0);
    double sum = 0.0;
    for (size_t i = 0; i < weights.size(); ++i) {
      const double w = (std::isfinite(weights[i]) && weights[i] > 0.f) ? weights[i] : 0.0;
      sum += w;
      cdf_[i + 1] = sum;
    }
    sum_ = sum;
    if (sum > 0.0) {
      for (size_t i = 0; i < weights.size(); ++i) {
        cdf_[i + 1] /= sum;
        pmf_[i] = float((cdf_[i + 1] - cdf_[i]));
      }
      cdf_.back() = 1.0;
    }
    build_guide();
  }

  size_t size() const { return pmf_.size(); }
  bool empty() const { return !(sum_ > 0.0); }
  double sum() const { return sum_; }
  float pmf(size_t i) const { return i < pmf_.size() ? pmf_[i] : 0.f; }
  // The normalised CDF at the upper end of bin i (what sample() searches).
  double cdf_upper(size_t i) const { return i + 1 < cdf_.size() ? cdf_[i + 1] : 1.0; }

  // Returns index; `u` is rescaled to a fresh uniform number in [0,1).
  // The inverse CDF by binary search; with a guide table (Chen & Asau's
  // cutpoint method) the search runs only over the bins bucket j = floor(u m)
  // can reach (and one on each side), which gives the same index as a search
  // over the whole table.
  size_t sample(float& u) const {
    const double x = u;
    auto first = cdf_.begin() + 1, last = cdf_.end();
    if (!guide_.empty()) {
      const size_t m = guide_.size() - 1;
      // one bucket of slack on each side: x * m and j / m are rounded
      const size_t j = std::min(size_t(x * double(m)), m - 1);
      first = cdf_.begin() + 1 + guide_[j > 0 ? j - 1 : 0];
      last = cdf_.begin() + 1 + std::min<size_t>(size_t(guide_[std::min(j + 2, m)]) + 1, pmf_.size());
    }
    auto it = std::upper_bound(first, last, x);
    size_t i = size_t(std::distance(cdf_.begin() + 1, it));
    i = std::min(i, pmf_.size() - 1);
    // skip zero-probability bins at the end of a run of equal cdf values
    while (pmf_[i] == 0.f && i + 1 < pmf_.size()) ++i;
    const double lo = cdf_[i], w = cdf_[i + 1] - cdf_[i];
    u = w > 0.0 ? float(std::clamp((x - lo) / w, 0.0, double(kOneMinusEps))) : 0.f;
    return i;
  }

 private:
  // Tables this small are searched whole (a few compares; no extra memory in
  // the many small per-leaf distributions of the guiding state).
  static constexpr size_t kGuideMin = 16;
  // guide_[j] = the index upper_bound(j / m) gives (m = guide_.size() - 1 =
  // number of bins): for u in [j/m, (j+1)/m) the index lies in
  // [guide_[j], guide_[j + 1]].
  void build_guide() {
    guide_.clear();
    const size_t n = pmf_.size();
    if (!(sum_ > 0.0) || n < kGuideMin) return;
    guide_.resize(n + 1);
    size_t i = 0;
    for (size_t j = 0; j <= n; ++j) {
      const double x = double(j) / double(n);
      while (i < n && cdf_[i + 1] <= x) ++i;
      guide_[j] = uint32_t(i);
    }
  }
  std::vector<float> pmf_;
  std::vector<double> cdf_;
  std::vector<uint32_t> guide_;
  double sum_ = 0.0;
};

// Piecewise-constant density on [0,1]^2 given a W x H grid of non-negative values.
class Distribution2D {
 public:
  Distribution2D() = default;
  void build(const std::vector<float>& values, int width, int height) {
    w_ = width;
    h_ = height;
    rows_.resize(height);
    std::vector<float> marg(height);
    for (int y = 0; y < height; ++y) {
      std::vector<float> row(values.begin() + size_t(y) * width, values.begin() + size_t(y + 1) * width);
      rows_[y].build(row);
      marg[y] = float(rows_[y].sum());
    }
    marginal_.build(marg);
  }
  bool empty() const { return marginal_.empty(); }

  // Returns a point in [0,1)^2 and its density w.r.t. area on [0,1]^2.
  Vec2 sample(Vec2 u, float& pdf) const {
    float uy = u.y, ux = u.x;
    const size_t y = marginal_.sample(uy);
    const size_t x = rows_[y].sample(ux);
    pdf = marginal_.pmf(y) * rows_[y].pmf(x) * float(w_) * float(h_);
    return Vec2((float(x) + ux) / float(w_), (float(y) + uy) / float(h_));
  }
  float pdf(const Vec2& p) const {
    const int x = std::clamp(int(p.x * w_), 0, w_ - 1), y = std::clamp(int(p.y * h_), 0, h_ - 1);
    return marginal_.pmf(size_t(y)) * rows_[size_t(y)].pmf(size_t(x)) * float(w_) * float(h_);
  }

 private:
  int w_ = 0, h_ = 0;
  std::vector<DiscreteDistribution> rows_;
  DiscreteDistribution marginal_;
};

}  // namespace mpg
