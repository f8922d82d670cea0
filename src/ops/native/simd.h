// Instruction-set helpers of calibconv's native kernels (deform.cpp, small_kernels.h): function
// multiversioning, forced inlining, and GCC vector types with unaligned loads and stores. Included
// once, by deform.cpp.
#pragma once

#include <cstring>
#include <type_traits>

namespace {

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

}  // namespace
