// A sub-path sample (MPG Sec. 5.5): the endpoints (x_D, x_L) of a solved
// chain, its first direction omega_D, its length n, its type tau and its
// weight w = T <1/P> (Eq. 9; with product sampling rho(x_D) T <1/P>, Eq. 14).
// 40 bytes: positions as floats, omega_D octahedral-encoded.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>

#include "core/math.h"
#include "core/rng.h"

namespace mpg {

struct SubpathSample {
  float xD[3];
  float xL[3];
  float dir[2];      // omega_D, octahedral map to [-1, 1]^2
  float weight;      // luminance of T <1/P> (or with the separator's BSDF)
  uint16_t tau;      // bit i set: vertex i is a reflection (R); n <= 16
  uint8_t n;         // chain length
  uint8_t flags;     // bit 0: a filtered copy (STree epsilon-overlap)

  static constexpr uint8_t kFiltered = 1;
  bool filtered() const { return (flags & kFiltered) != 0; }
  Vec3 pD() const { return Vec3(xD[0], xD[1], xD[2]); }
  Vec3 pL() const { return Vec3(xL[0], xL[1], xL[2]); }
};
static_assert(sizeof(SubpathSample) == 40, "SubpathSample must stay 40 bytes");

// A read-only view of contiguous samples.
struct SampleSpan {
  const SubpathSample* data = nullptr;
  size_t size = 0;
  const SubpathSample* begin() const { return data; }
  const SubpathSample* end() const { return data + size; }
};

// A 64-bit hash of a sample's content (the flags excluded). It gives the
// samples a canonical order, so that the guiding state built from a set of
// samples does not depend on the order the renderer's threads delivered them
// in, and it seeds the per-sample jitter of stochastic filtering.
inline uint64_t content_key(const SubpathSample& s) {
  SubpathSample c = s;
  c.flags = 0;
  uint64_t w[5];
  std::memcpy(w, &c, sizeof(w));
  uint64_t h = 0x51ed270b27ad5f3bULL;
  for (uint64_t x : w) h = mix64(h ^ x);
  return h;
}
// A total order on sample contents (ties of the key broken by the bytes;
// samples equal in both are interchangeable).
inline bool canonical_less(uint64_t ka, const SubpathSample& a, uint64_t kb, const SubpathSample& b) {
  if (ka != kb) return ka < kb;
  return std::memcmp(&a, &b, sizeof(SubpathSample)) < 0;
}

// Octahedral encoding of unit vectors (Meyer et al. 2010; Cigolle et al. 2014, JCGT 3(2)).
inline Vec2 oct_encode(const Vec3& v) {
  const float l1 = std::abs(v.x) + std::abs(v.y) + std::abs(v.z);
  Vec2 p(v.x / l1, v.y / l1);
  if (v.z < 0.f) {
    p = Vec2((1.f - std::abs(p.y)) * (p.x >= 0.f ? 1.f : -1.f),
             (1.f - std::abs(p.x)) * (p.y >= 0.f ? 1.f : -1.f));
  }
  return p;
}
inline Vec3 oct_decode(const Vec2& e) {
  Vec3 v(e.x, e.y, 1.f - std::abs(e.x) - std::abs(e.y));
  if (v.z < 0.f) {
    const float x = v.x;
    v.x = (1.f - std::abs(v.y)) * (x >= 0.f ? 1.f : -1.f);
    v.y = (1.f - std::abs(x)) * (v.y >= 0.f ? 1.f : -1.f);
  }
  return glm::normalize(v);
}

inline uint16_t tau_bits(const char* tau, int n) {
  uint16_t b = 0;
  for (int i = 0; i < n && i < 16; ++i)
    if (tau[i] == 'R') b = uint16_t(b | (1u << i));
  return b;
}

}  // namespace mpg
