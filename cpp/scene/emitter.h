// Emitters: area (on any shape), point, spot, directional, constant, envmap.
#pragma once

#include "core/distribution.h"
#include "core/math.h"
#include "scene/texture.h"

namespace mpg {

struct Emitter {
  enum class Type { Area, Point, Spot, Directional, Constant, Envmap };
  Type type = Type::Area;
  Color value{0.f};        // radiance (area, constant), intensity (point, spot), irradiance (directional)
  int shape = -1;
  Vec3 position{0.f};
  Vec3 direction{0.f, 0.f, 1.f};   // directional: direction light travels
  Frame frame;                      // spot: local z = axis; envmap: world<-local rotation (s,t,n)
  float cos_cutoff = 0.f, cos_beam = 0.f, cutoff = 0.f, inv_transition = 0.f;
  Texture env;                      // envmap image (lat-long)
  Distribution2D env_dist;
  float scale = 1.f;
  float power = 0.f;                // selection weight

  bool is_delta() const { return type == Type::Point || type == Type::Spot || type == Type::Directional; }
  bool is_infinite() const {
    return type == Type::Directional || type == Type::Constant || type == Type::Envmap;
  }

  // Spot falloff (Mitsuba 3's spot: linear in angle between beam width and cutoff).
  float spot_falloff(const Vec3& local_dir) const {
    const float c = local_dir.z;
    if (c <= cos_cutoff) return 0.f;
    if (c >= cos_beam) return 1.f;
    return std::clamp((cutoff - safe_acos(c)) * inv_transition, 0.f, 1.f);
  }

  // Envmap: world direction -> uv (Mitsuba 3 convention: u = atan2(x, -z)/2pi, v = acos(y)/pi
  // in the emitter's local frame, where frame.s/t/n are the images of local x/y/z).
  Vec2 env_uv(const Vec3& d_world) const {
    const Vec3 d = frame.to_local(d_world);
    float u = std::atan2(d.x, -d.z) * kInv2Pi;
    u -= std::floor(u);
    return Vec2(u, safe_acos(d.y) * kInvPi);
  }
  Vec3 env_dir(const Vec2& uv) const {
    const float phi = uv.x * 2.f * kPi, theta = uv.y * kPi;
    const float st = std::sin(theta);
    return frame.to_world(Vec3(st * std::sin(phi), std::cos(theta), -st * std::cos(phi)));
  }
  // Lat-long lookup with Mitsuba 3's envmap convention (so the same file gives
  // the same light): texel x is centred at u = (x + 0.5) / W and wraps around;
  // row y sits at v = y / (H - 1), so the first and last rows are the poles.
  Color env_lookup(const Vec2& uv) const {
    const int W = env.width, H = env.height;
    float fx = uv.x * float(W) - 0.5f;
    fx -= std::floor(fx / float(W)) * float(W);
    const float fy = std::clamp(uv.y, 0.f, 1.f) * float(H - 1);
    const int x0 = std::min(int(fx), W - 1), y0 = std::min(int(fy), std::max(H - 2, 0));
    const float ax = fx - float(x0), ay = fy - float(y0);
    const int x1 = (x0 + 1) % W, y1 = std::min(y0 + 1, H - 1);
    auto t = [&](int x, int y) {
      const float* p = &env.data[(size_t(y) * W + x) * 3];
      return Color(p[0], p[1], p[2]);
    };
    return ((1 - ax) * (1 - ay)) * t(x0, y0) + (ax * (1 - ay)) * t(x1, y0) +
           ((1 - ax) * ay) * t(x0, y1) + (ax * ay) * t(x1, y1);
  }
  Color eval_env(const Vec3& d_world) const {
    if (type == Type::Constant) return value;
    if (type != Type::Envmap) return Color(0.f);
    return env_lookup(env_uv(d_world)) * scale;
  }
  // Solid-angle density of sampling an escaped direction (without selection probability).
  float pdf_env(const Vec3& d_world) const {
    if (type == Type::Constant) return kInv4Pi;
    if (type != Type::Envmap) return 0.f;
    const Vec2 uv = env_uv(d_world);
    const float st = std::sin(uv.y * kPi);
    if (!(st > 1e-7f)) return 0.f;
    return env_dist.pdf(uv) / (2.f * kPi * kPi * st);
  }
};

}  // namespace mpg
