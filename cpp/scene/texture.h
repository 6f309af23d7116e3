// Textures: constant, bitmap (bilinear/nearest, repeat/mirror/clamp), checkerboard.
#pragma once

#include <vector>

#include "core/math.h"

namespace mpg {

struct Texture {
  enum class Kind { Constant, Bitmap, Checkerboard };
  enum class Wrap { Repeat, Mirror, Clamp };
  Kind kind = Kind::Constant;
  Color value{0.f}, color0{0.4f}, color1{0.2f};
  std::vector<float> data;  // H x W x 3, row 0 sampled at v = 0
  int width = 0, height = 0;
  Mat3 to_uv{1.f};          // applied to (u, v, 1)
  bool bilinear = true;
  Wrap wrap = Wrap::Repeat;

  Color texel(int x, int y) const {
    x = wrap_index(x, width);
    y = wrap_index(y, height);
    const float* p = &data[(size_t(y) * width + x) * 3];
    return Color(p[0], p[1], p[2]);
  }

  Color eval(const Vec2& uv_in) const {
    if (kind == Kind::Constant) return value;
    const Vec3 q = to_uv * Vec3(uv_in, 1.f);
    const Vec2 uv(q.x, q.y);
    if (kind == Kind::Checkerboard) {
      const float fu = uv.x - std::floor(uv.x), fv = uv.y - std::floor(uv.y);
      return ((fu > 0.5f) == (fv > 0.5f)) ? color0 : color1;
    }
    if (!(std::isfinite(uv.x) && std::isfinite(uv.y))) return Color(0.f);
    const float x = uv.x * width, y = uv.y * height;
    if (!bilinear) return texel(int(std::floor(x)), int(std::floor(y)));
    const float fx = x - 0.5f, fy = y - 0.5f;
    const int x0 = int(std::floor(fx)), y0 = int(std::floor(fy));
    const float ax = fx - x0, ay = fy - y0;
    return (1 - ax) * (1 - ay) * texel(x0, y0) + ax * (1 - ay) * texel(x0 + 1, y0) +
           (1 - ax) * ay * texel(x0, y0 + 1) + ax * ay * texel(x0 + 1, y0 + 1);
  }

  float mean_value() const {
    if (kind == Kind::Constant) return mean(value);
    if (kind == Kind::Checkerboard) return 0.5f * (mean(color0) + mean(color1));
    double s = 0.0;
    for (float v : data) s += v;
    return data.empty() ? 0.f : float(s / double(data.size()));
  }

 private:
  int wrap_index(int i, int n) const {
    switch (wrap) {
      case Wrap::Clamp: return std::clamp(i, 0, n - 1);
      case Wrap::Mirror: {
        int m = i % (2 * n);
        if (m < 0) m += 2 * n;
        return m < n ? m : 2 * n - 1 - m;
      }
      default: {
        int m = i % n;
        return m < 0 ? m + n : m;
      }
    }
  }
};

}  // namespace mpg
