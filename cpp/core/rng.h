// PCG32 (O'Neill 2014, pcg-random.org: 64-bit LCG state, XSH-RR output) and the
// stream keying that makes renders independent of thread scheduling.
#pragma once

#include <cstdint>

namespace mpg {

class PCG32 {
 public:
  PCG32() { seed(0x853c49e6748fea9bULL, 0xda3e39cb94b95bdbULL); }
  PCG32(uint64_t initstate, uint64_t initseq) { seed(initstate, initseq); }

  void seed(uint64_t initstate, uint64_t initseq) {
    state_ = 0u;
    inc_ = (initseq << 1u) | 1u;
    next_u32();
    state_ += initstate;
    next_u32();
  }

  uint32_t next_u32() {
    const uint64_t old = state_;
    state_ = old * 6364136223846793005ULL + inc_;
    const uint32_t xorshifted = uint32_t(((old >> 18u) ^ old) >> 27u);
    const uint32_t rot = uint32_t(old >> 59u);
    return (xorshifted >> rot) | (xorshifted << ((~rot + 1u) & 31));
  }

  // Uniform in [0, 1): 23 random mantissa bits.
  float next_float() {
    union { uint32_t u; float f; } x;
    x.u = (next_u32() >> 9) | 0x3f800000u;
    return x.f - 1.f;
  }

  double next_double() {
    const uint64_t hi = next_u32(), lo = next_u32();
    return double(((hi << 32) | lo) >> 11) * 0x1.0p-53;
  }

 private:
  uint64_t state_ = 0, inc_ = 1;
};

// SplitMix64 finaliser: a strong 64-bit mix used to derive stream keys.
inline uint64_t mix64(uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

// The random stream of one sample depends on (seed, pass, pixel, sample index) only.
inline PCG32 make_stream(uint64_t seed, uint64_t pass, uint64_t pixel, uint64_t sample) {
  const uint64_t a = mix64(seed ^ mix64(pass + 0x632be59bd9b4e019ULL));
  const uint64_t b = mix64(pixel ^ mix64(sample + 0x8cb92ba72f3d8dd7ULL));
  return PCG32(mix64(a ^ b), mix64(a + 0x2545f4914f6cdd1dULL) ^ b);
}

}  // namespace mpg
