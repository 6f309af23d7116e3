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

// The first two dimensions of Sobol's sequence, a (0,2)-sequence in base 2
// (Sobol 1967; dimension 0 is van der Corput's radical inverse, dimension 1's
// generator matrix is Pascal's triangle mod 2). Every block of 2^m points
// starting at a multiple of 2^m puts one point in each elementary interval
// [a 2^-j, (a+1) 2^-j) x [b 2^-(m-j), (b+1) 2^-(m-j)), for every j = 0..m.
inline uint32_t sobol_dim0(uint32_t i) {
  i = (i << 16) | (i >> 16);
  i = ((i & 0x00ff00ffu) << 8) | ((i & 0xff00ff00u) >> 8);
  i = ((i & 0x0f0f0f0fu) << 4) | ((i & 0xf0f0f0f0u) >> 4);
  i = ((i & 0x33333333u) << 2) | ((i & 0xccccccccu) >> 2);
  i = ((i & 0x55555555u) << 1) | ((i & 0xaaaaaaaau) >> 1);
  return i;
}

inline uint32_t sobol_dim1(uint32_t i) {
  uint32_t x = 0, v = 0x80000000u;
  for (; i; i >>= 1, v ^= v >> 1)
    if (i & 1u) x ^= v;
  return x;
}

// Point i of the pixel's 2D sequence, randomly digitally shifted: XORed with
// the pixel's own uniform random 32-bit words (shift0, shift1). XOR with fixed
// bits maps the dyadic intervals of each shape one to one onto themselves, so
// the net property above is kept; XOR with uniform random bits makes each
// point, on its own, exactly uniform on the 2^-32 grid, so every sample stays
// an unbiased estimate and only the samples of one pixel are correlated (the
// stratification). Returned as floats on the 2^-24 grid.
inline void shifted_sobol_2d(uint32_t i, uint32_t shift0, uint32_t shift1, float& u0, float& u1) {
  u0 = float((sobol_dim0(i) ^ shift0) >> 8) * 0x1.0p-24f;
  u1 = float((sobol_dim1(i) ^ shift1) >> 8) * 0x1.0p-24f;
}

// The random stream of one sample depends on (seed, pass, pixel, sample index) only.
inline PCG32 make_stream(uint64_t seed, uint64_t pass, uint64_t pixel, uint64_t sample) {
  const uint64_t a = mix64(seed ^ mix64(pass + 0x632be59bd9b4e019ULL));
  const uint64_t b = mix64(pixel ^ mix64(sample + 0x8cb92ba72f3d8dd7ULL));
  return PCG32(mix64(a ^ b), mix64(a + 0x2545f4914f6cdd1dULL) ^ b);
}

}  // namespace mpg
