#include "scene/camera.h"

namespace mpg {

void FilterSampler::build(Type t, float stddev, float tent_radius) {
  type = t;
  cdf.clear();
  if (t == Type::Box) {
    radius = 0.5f;
    return;
  }
  const int n = 4096;
  std::vector<double> w(n);
  if (t == Type::Gaussian) {
    // Mitsuba 3's gaussian: radius 4 sigma, exp(-x^2 / (2 sigma^2)) minus its value at the radius.
    radius = 4.f * stddev;
    const double alpha = -1.0 / (2.0 * double(stddev) * stddev);
    const double bias = std::exp(alpha * double(radius) * radius);
    for (int i = 0; i < n; ++i) {
      const double x = -radius + (i + 0.5) * (2.0 * radius / n);
      w[i] = std::max(0.0, std::exp(alpha * x * x) - bias);
    }
  } else {
    radius = tent_radius;
    for (int i = 0; i < n; ++i) {
      const double x = -radius + (i + 0.5) * (2.0 * radius / n);
      w[i] = std::max(0.0, 1.0 - std::abs(x) / radius);
    }
  }
  cdf.assign(n + 1, 0.f);
  double s = 0.0;
  for (int i = 0; i < n; ++i) {
    s += w[i];
    cdf[i + 1] = float(s);
  }
  for (auto& c : cdf) c = float(c / s);
  cdf.back() = 1.f;
}

float FilterSampler::sample(float u) const {
  if (type == Type::Box) return u - 0.5f;
  const int n = int(cdf.size()) - 1;
  auto it = std::upper_bound(cdf.begin() + 1, cdf.end(), u);
  int i = std::min(int(std::distance(cdf.begin() + 1, it)), n - 1);
  const float w = cdf[i + 1] - cdf[i];
  const float f = w > 0.f ? (u - cdf[i]) / w : 0.5f;
  return -radius + (float(i) + f) * (2.f * radius / float(n));
}

}  // namespace mpg
