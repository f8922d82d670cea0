// Instruction-set helpers of calibconv's native kernels (src/ops/native): function
// multiversioning, forced inlining, GCC vector types with unaligned loads and stores, and the 8x8
// register transpose.
#pragma once

#include <cstdint>
#include <cstring>
#include <type_traits>

namespace calibconv::native {

// Instruction sets: the inner loops (gather, scatter) are compiled for several and picked at
// load time (GCC function multiversioning, see CALIBCONV_TILE_KERNELS below).

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define CALIBCONV_CLONES \
  __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CALIBCONV_CLONES
#endif

#if defined(__GNUC__)
#define CALIBCONV_ALWAYS_INLINE __attribute__((always_inline))
#define CALIBCONV_IVDEP _Pragma("GCC ivdep")
#else
#define CALIBCONV_ALWAYS_INLINE
#define CALIBCONV_IVDEP
#endif

// Vectors of N elements of T (GCC/Clang vector extensions, lowered to the widest registers the
// clone's instruction set has): for channel counts whose byte size is a power of two, the gather
// and scatter of one corner are written as whole-vector operations, because GCC's
// auto-vectoriser leaves these short fixed loops scalar (it cannot prove the tile and the
// buffer apart after unrolling them).
template <typename T, int N, typename = void>
struct VecOf {
  static constexpr bool ok = false;
};
#if defined(__GNUC__)
template <typename T, int N>
struct VecOf<T, N, std::enable_if_t<(N >= 4 && (N & (N - 1)) == 0)>> {
  static constexpr bool ok = true;
  typedef T type __attribute__((vector_size(N * sizeof(T))));
};
#endif
// (Always inlined, internal: -Wpsabi's note about passing wide vectors by value does not apply.)
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"
#endif
template <typename V, typename T>
CALIBCONV_ALWAYS_INLINE inline V load(const T* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V, typename T>
CALIBCONV_ALWAYS_INLINE inline void store(T* p, const V& v) {
  std::memcpy(p, &v, sizeof(V));
}


// Transposes the 8x8 block of floats with row i at src[i] into the rows dst[j] (each row its own
// pointer): three rounds of shuffles (pairs, quads, halves) on eight 8-float vectors, the register
// transpose of the AVX instruction set, written with GCC's generic shuffles so that every clone
// gets its own instructions.
CALIBCONV_ALWAYS_INLINE inline void transpose8x8_rows(const float* const (&src)[8],
                                                      float* const (&dst)[8]) {
#if defined(__GNUC__) && !defined(__clang__)
  using V = VecOf<float, 8>::type;
  typedef int32_t M __attribute__((vector_size(32)));
  V r[8], t[8], u[8];
  for (int i = 0; i < 8; ++i) r[i] = load<V>(src[i]);
  for (int i = 0; i < 8; i += 2) {
    t[i] = __builtin_shuffle(r[i], r[i + 1], M{0, 8, 1, 9, 4, 12, 5, 13});
    t[i + 1] = __builtin_shuffle(r[i], r[i + 1], M{2, 10, 3, 11, 6, 14, 7, 15});
  }
  for (int i = 0; i < 8; i += 4) {
    for (int h = 0; h < 2; ++h) {
      u[i + 2 * h] = __builtin_shuffle(t[i + h], t[i + h + 2], M{0, 1, 8, 9, 4, 5, 12, 13});
      u[i + 2 * h + 1] =
          __builtin_shuffle(t[i + h], t[i + h + 2], M{2, 3, 10, 11, 6, 7, 14, 15});
    }
  }
  for (int j = 0; j < 4; ++j) {
    store(dst[j], __builtin_shuffle(u[j], u[j + 4], M{0, 1, 2, 3, 8, 9, 10, 11}));
    store(dst[j + 4], __builtin_shuffle(u[j], u[j + 4], M{4, 5, 6, 7, 12, 13, 14, 15}));
  }
#else
  for (int i = 0; i < 8; ++i)
    for (int j = 0; j < 8; ++j) dst[j][i] = src[i][j];
#endif
}

}  // namespace calibconv::native
