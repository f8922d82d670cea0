// The few-output-channel kernels of calibconv's deformable convolution (float32, one group, C_out
// 8 to 1024 with AVX-512, 8 to 32 with AVX2; weights up to SMALL_MAX_WEIGHT): register-blocked
// products on L1-sized blocks of gathered columns (larger blocks, in slabs, for large weights),
// compiled per instruction-set level and picked at run time. Header-only (the layer calls them
// through small_kernels_for, tools/product_harness.cpp times them alone). What was measured for
// the block sizes and limits below: docs/bench/cpu-kernels.md.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>

#include "simd.h"

namespace calibconv::native {

// Few output channels (float32, one group, C_out 8, 16, 32, 64, 128, 256, 512 or 1024 with AVX-512;
// 8, 16 or 32 with AVX2, see below; a weight of at most SMALL_MAX_WEIGHT values): the three
// products of a pass through register-blocked kernels on blocks of SMALL_BLOCK_BYTES of columns
// instead of a oneDNN / BLAS call per tile. At these shapes a GEMM call costs more in packing and
// overhead than in arithmetic (with 64 and 128 outputs the AVX-512 kernels are faster than oneDNN
// even on large maps), and its column tile (megabytes, so that the call is worth it) makes a round
// trip through the caches; here a block of pixels is gathered into an L1-sized buffer and
// multiplied at once, its columns still in L1. The accumulators of a block of pixels stay in
// registers over the whole reduction.
//
// Register blocking depends on the instruction set, so these kernels are compiled once per
// level with their own block sizes and picked at run time (small_isa), not by GCC's
// target_clones (one body for all levels): a row of 32 outputs is 2 AVX-512 registers but 4
// AVX2 ones, and with AVX-512's block sizes the AVX2 body spills its accumulators to the stack
// (and a 128-byte vector type spills them even with AVX-512: GCC keeps such vectors in memory).
// Vectors are at most 16 floats; a block of R rows (forward) or JB columns (weight gradient)
// holds R * OC / L accumulators of L floats for OC of the outputs at a time, sized to leave
// registers for the weights and the broadcast (C_out 8 / 16 / 32 / 64; 128 to 1024 as passes of
// 64):
//   AVX-512 (32 registers of 16 floats): forward R = 8 / 12 / 12 / 6, JB = 12 / 12 / 8 / 6,
//                                        all outputs at once; column gradient 8 rows x 3
//                                        vectors (4 x 4 at 8 outputs, 6 x 4 at 256 to 1024);
//   AVX2 (16 registers of 8 floats):     forward R = 8 / 6 / 2, JB = 8 / 4 / 2 (8 / 16 / 32
//                                        outputs; 64 and 128 go through the BLAS, which beat
//                                        passes of 32); column gradient 4 x 3.
// The AVX-512 sizes suit an Intel Xeon with 48 KiB of L1d (with R = 4 the forward of 64 outputs
// streams its weight panel from L2 faster than L2 sustains). Blocks of fewer rows than R finish
// four rows at a time, then one.
// The arithmetic of every output element (one fused multiply-add per reduction step, in the
// same order) is the same at both levels, so where both have kernels they give identical
// results. CPUs without AVX2 and FMA (and other architectures) use the oneDNN / BLAS path.

constexpr int64_t SMALL_BLOCK_BYTES = 16 << 10;

// Outputs of a panel of the weight (and of its gradient) as the forward and weight-gradient
// kernels read it: [K*C, C_out] is stored as C_out / P panels [K*C, P], one after the other, P =
// small_panel(C_out), the outputs of one pass. The rows of the weight that a pass multiplies
// (a slab's, or before that a 16 KiB chunk's, rows of P values) are then contiguous. In the
// plain [K*C, C_out] layout they were pieces of 256 bytes at a stride of C_out * 4 bytes, which
// (with 256 and 512 outputs) fell on few of L1's sets and did not stay there.
constexpr int64_t SMALL_PANEL = 64;
constexpr int64_t small_panel(int64_t cout) { return std::min(cout, SMALL_PANEL); }

// Rows of a block at least: with many input channels a block of SMALL_BLOCK_BYTES would be a few
// rows, and every block reads the whole weight (from L2 once it outgrows L1); 24 rows keep the
// reads of the weight below those of the columns (one row of 64 channels is 2.3 KiB of columns).
constexpr int64_t SMALL_BLOCK_MIN_ROWS = 24;

// A weight of more than SMALL_LARGE_WEIGHT values (1 MiB) no longer stays in L2 from one block to
// the next: every block reads it from L3 (the forward and the column gradient) or reads and
// writes its gradient there (the weight gradient). Blocks of such layers have
// SMALL_LARGE_BLOCK_ROWS rows, so the weight is read once per 256 rows instead of 24, and the
// forward and weight gradient run through the columns in slabs of SMALL_SLAB reduction steps
// (a slab of a block's columns, 512 KiB, stays in L2 while every pass multiplies it).
constexpr int64_t SMALL_LARGE_WEIGHT = 1 << 18;
constexpr int64_t SMALL_LARGE_BLOCK_ROWS = 256;
constexpr int64_t SMALL_SLAB = 512;
constexpr bool small_large_weight(int64_t kc, int64_t cout) {
  return kc * cout > SMALL_LARGE_WEIGHT;
}
// The columns a block's gathered row holds for the few-output-channel kernels (its row stride):
// a slab of a large weight's, else all kc (gather.h's column_slabs, tools/product_harness.cpp).
constexpr int64_t small_slab_width(int64_t kc, int64_t cout) {
  return small_large_weight(kc, cout) ? std::min(kc, SMALL_SLAB) : kc;
}
// The end of the slab that column a is in (slabs counted from column 0), at most s1.
constexpr int64_t slab_end(int64_t a, int64_t s1) {
  return std::min(s1, (a / SMALL_SLAB + 1) * SMALL_SLAB);
}

// Rows of a block of `kc` columns each, for `cout` outputs, within a tile of `tile` rows: a
// multiple of 8 that fits SMALL_BLOCK_BYTES, at least SMALL_BLOCK_MIN_ROWS (or
// SMALL_LARGE_BLOCK_ROWS for a large weight), at most the tile.
inline int64_t small_block_rows(int64_t kc, int64_t cout, int64_t tile) {
  const int64_t rows = SMALL_BLOCK_BYTES / (kc * static_cast<int64_t>(sizeof(float)));
  const int64_t least =
      small_large_weight(kc, cout) ? SMALL_LARGE_BLOCK_ROWS : SMALL_BLOCK_MIN_ROWS;
  return std::min(tile, std::max<int64_t>(least, rows - rows % 8));
}

// The register tile of every product below: acc[r][v] += sum over k in [k0, k1) of
// a[r * ars + k * aks] * b[k * brs + v * L], R rows of a (one scalar each, broadcast) against
// NV vectors of L floats of a row of b, all R x NV accumulators in registers. Each element adds
// its products in the order of k (one fused multiply-add each), whatever R, NV and L: the
// results do not depend on the register blocking. tile_step is one step k.
//
// Four steps an iteration: GCC does not unroll the loop over k by itself, and with one step an
// iteration the loop's add, compare and branch kept the two FMA units from their peak (the same
// bits either way).
template <int R, int NV, int L>
CALIBCONV_ALWAYS_INLINE inline void tile_step(typename VecOf<float, L>::type (&acc)[R][NV],
                                              const float* a, int64_t ars, int64_t aks,
                                              const float* b, int64_t brs, int64_t k) {
  using V = typename VecOf<float, L>::type;
  V w[NV];
#pragma GCC unroll 4
  for (int v = 0; v < NV; ++v) w[v] = load<V>(b + k * brs + v * L);
#pragma GCC unroll 16
  for (int r = 0; r < R; ++r) {
    const float s = a[r * ars + k * aks];
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) acc[r][v] += s * w[v];
  }
}
template <int R, int NV, int L>
CALIBCONV_ALWAYS_INLINE inline void tile_product(typename VecOf<float, L>::type (&acc)[R][NV],
                                                 const float* a, int64_t ars, int64_t aks,
                                                 const float* b, int64_t brs, int64_t k0,
                                                 int64_t k1) {
  int64_t k = k0;
  for (; k + 4 <= k1; k += 4) {
#pragma GCC unroll 4
    for (int u = 0; u < 4; ++u) tile_step<R, NV, L>(acc, a, ars, aks, b, brs, k + u);
  }
  for (; k < k1; ++k) tile_step<R, NV, L>(acc, a, ars, aks, b, brs, k);
}

// acc[r][v] = p[r * rs + v * L] (load), or the reverse (store).
template <int R, int NV, int L>
CALIBCONV_ALWAYS_INLINE inline void tile_load(typename VecOf<float, L>::type (&acc)[R][NV],
                                              const float* p, int64_t rs) {
#pragma GCC unroll 16
  for (int r = 0; r < R; ++r) {
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) {
      acc[r][v] = load<typename VecOf<float, L>::type>(p + r * rs + v * L);
    }
  }
}
template <int R, int NV, int L>
CALIBCONV_ALWAYS_INLINE inline void tile_store(const typename VecOf<float, L>::type (&acc)[R][NV],
                                               float* p, int64_t rs) {
#pragma GCC unroll 16
  for (int r = 0; r < R; ++r) {
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) store(p + r * rs + v * L, acc[r][v]);
  }
}

// Rows [t, t + R) of the forward over the reduction chunk [j0, j1), from the bias (j0 = 0) or
// the partial sums in y; cols holds the columns from s0 on, rows ldc apart. (Helpers are
// always-inlined functions, not lambdas: a lambda would not take the instruction set of the
// function it is written in.)
template <int CS, int NV, int L, int R>
CALIBCONV_ALWAYS_INLINE inline void small_forward_rows(const float* cols, int64_t ldc,
                                                       int64_t s0, const float* wt,
                                                       const float* bias, float* y, int64_t t,
                                                       int64_t j0, int64_t j1) {
  using V = typename VecOf<float, L>::type;
  V acc[R][NV];
  if (j0 > 0) {
    tile_load<R, NV, L>(acc, y + t * CS, CS);
  } else {
#pragma GCC unroll 16
    for (int r = 0; r < R; ++r) {
#pragma GCC unroll 4
      for (int v = 0; v < NV; ++v) acc[r][v] = bias ? load<V>(bias + v * L) : V{};
    }
  }
  tile_product<R, NV, L>(acc, cols + t * ldc + (j0 - s0), ldc, 1, wt + j0 * NV * L, NV * L, 0,
                         j1 - j0);
  tile_store<R, NV, L>(acc, y + t * CS, CS);
}

// y[t, :] = bias + cols[t, :] @ wt for t in [0, n) and CO of the outputs, over the reduction
// range [r0, r1) (at most a slab) within the columns cols holds, [s0, ...) at row stride ldc: wt
// [kc, CO] (a panel of the weight, transposed, rows of CO values), y [n, CO] (row stride CS) with
// the partial sums of [0, r0) unless r0 = 0; bias may be null. R rows at a time (then one), each
// with CO / L accumulators of L floats, in registers over the whole range: the range's rows of
// the panel (up to 128 KiB) are read in order, from L2, once per R rows (faster than chunks that
// stay in L1 with the partial sums stored and loaded back between chunks).
template <int CS, int CO, int L, int R>
CALIBCONV_ALWAYS_INLINE inline void small_forward_range(const float* cols, int64_t n, int64_t ldc,
                                                        int64_t s0, const float* wt,
                                                        const float* bias, float* y, int64_t r0,
                                                        int64_t r1) {
  constexpr int NV = CO / L;
  int64_t t = 0;
  for (; t + R <= n; t += R) {
    small_forward_rows<CS, NV, L, R>(cols, ldc, s0, wt, bias, y, t, r0, r1);
  }
  if constexpr (R > 4) {
    for (; t + 4 <= n; t += 4) {
      small_forward_rows<CS, NV, L, 4>(cols, ldc, s0, wt, bias, y, t, r0, r1);
    }
  }
  for (; t < n; ++t) small_forward_rows<CS, NV, L, 1>(cols, ldc, s0, wt, bias, y, t, r0, r1);
}

// The forward of all CO outputs over the reduction range [s0, s1) (the columns cols holds, at
// row stride ldc; y holds the partial sums of [0, s0)), OC outputs at a time (fewer accumulators
// than a row of CO needs): wt holds CO / OC panels [kc, OC], one after the other (small_panel).
// In slabs of SMALL_SLAB steps counted from 0 (a block's slab of columns stays in L2 while every
// pass multiplies it). Every element adds its products in the order of k, whatever the slabs.
template <int CO, int L, int R, int OC>
CALIBCONV_ALWAYS_INLINE inline void small_forward_body(const float* cols, int64_t n, int64_t ldc,
                                                       int64_t kc, int64_t s0, int64_t s1,
                                                       const float* wt, const float* bias,
                                                       float* y) {
  for (int64_t a = s0, b; a < s1; a = b) {
    b = slab_end(a, s1);
    for (int o0 = 0; o0 < CO; o0 += OC) {
      small_forward_range<CO, OC, L, R>(cols, n, ldc, s0, wt + o0 * kc,
                                        bias ? bias + o0 : nullptr, y + o0, a, b);
    }
  }
}

// g[t, j0 + i] = gy[t, :] @ w[:, j0 + i] for i < J * L and t in [0, n): R rows at a time (then
// one), R x J accumulators.
template <int CO, int L, int R, int J>
CALIBCONV_ALWAYS_INLINE inline void small_column_rows(const float* gy, int64_t kc, const float* w,
                                                      float* g, int64_t j0, int64_t t) {
  typename VecOf<float, L>::type acc[R][J] = {};
  tile_product<R, J, L>(acc, gy + t * CO, CO, 1, w + j0, kc, 0, CO);
  tile_store<R, J, L>(acc, g + t * kc + j0, kc);
}

template <int CO, int L, int R, int J>
CALIBCONV_ALWAYS_INLINE inline void small_column_chunk(const float* gy, int64_t n, int64_t kc,
                                                       const float* w, float* g, int64_t j0) {
  int64_t t = 0;
  for (; t + R <= n; t += R) small_column_rows<CO, L, R, J>(gy, kc, w, g, j0, t);
  if constexpr (R > 4) {
    for (; t + 4 <= n; t += 4) small_column_rows<CO, L, 4, J>(gy, kc, w, g, j0, t);
  }
  for (; t < n; ++t) small_column_rows<CO, L, 1, J>(gy, kc, w, g, j0, t);
}

// g[t, :] = gy[t, :] @ w for t in [0, n): gy [n, CO] (row stride CO), w [CO, kc] (the packed
// weight), g [n, kc]; kc a multiple of 8. Chunks of J vectors of L columns (the chunk's CO rows
// of the weight stay in L1 over all rows of the block), then single vectors of L, then of 8
// columns.
template <int CO, int L, int R, int J>
CALIBCONV_ALWAYS_INLINE inline void small_column_gradient_body(const float* gy, int64_t n,
                                                               int64_t kc, const float* w,
                                                               float* g) {
  int64_t j0 = 0;
  for (; j0 + J * L <= kc; j0 += J * L) small_column_chunk<CO, L, R, J>(gy, n, kc, w, g, j0);
  for (; j0 + L <= kc; j0 += L) small_column_chunk<CO, L, R, 1>(gy, n, kc, w, g, j0);
  if constexpr (L > 8) {
    for (; j0 + 8 <= kc; j0 += 8) small_column_chunk<CO, 8, R, 1>(gy, n, kc, w, g, j0);
  }
}

// acc[j, :] += sum over t in [0, n) of cols[t, j] * gy[t, :] for CO of the outputs: cols holds
// the columns from s0 on at row stride ldc, gy [n, CO] (row stride CS), acc [kc, CO] (a panel of
// the weight gradient, transposed, rows of CO values). JB columns at a time (then one), their
// CO / L accumulators each in registers over all n rows.
template <int CS, int NV, int L, int JB>
CALIBCONV_ALWAYS_INLINE inline void small_weight_columns(const float* cols, int64_t n,
                                                         int64_t ldc, int64_t s0,
                                                         const float* gy, float* acc,
                                                         int64_t j0) {
  typename VecOf<float, L>::type a[JB][NV];
  tile_load<JB, NV, L>(a, acc + j0 * NV * L, NV * L);
  tile_product<JB, NV, L>(a, cols + (j0 - s0), 1, ldc, gy, CS, 0, n);
  tile_store<JB, NV, L>(a, acc + j0 * NV * L, NV * L);
}

template <int CS, int CO, int L, int JB>
CALIBCONV_ALWAYS_INLINE inline void small_weight_gradient_chunk(const float* cols, int64_t n,
                                                                int64_t ldc, int64_t s0,
                                                                const float* gy, float* acc,
                                                                int64_t r0, int64_t r1) {
  constexpr int NV = CO / L;
  int64_t j0 = r0;
  for (; j0 + JB <= r1; j0 += JB) {
    small_weight_columns<CS, NV, L, JB>(cols, n, ldc, s0, gy, acc, j0);
  }
  if constexpr (JB > 4) {
    for (; j0 + 4 <= r1; j0 += 4) {
      small_weight_columns<CS, NV, L, 4>(cols, n, ldc, s0, gy, acc, j0);
    }
  }
  for (; j0 < r1; ++j0) small_weight_columns<CS, NV, L, 1>(cols, n, ldc, s0, gy, acc, j0);
}

// The weight gradient of the outputs [o_begin, o_end) of CO (whole panels) over the columns
// [s0, s1) (which cols holds at row stride ldc), OC outputs at a time, each into its panel
// [kc, OC] of acc (CO / OC panels, as wt); in slabs of SMALL_SLAB columns counted from 0, as
// small_forward_body. Each element of acc sums over the rows in their order, whatever the range.
template <int CO, int L, int JB, int OC>
CALIBCONV_ALWAYS_INLINE inline void small_weight_gradient_body(const float* cols, int64_t n,
                                                               int64_t ldc, int64_t kc,
                                                               int64_t s0, int64_t s1,
                                                               const float* gy, float* acc,
                                                               int64_t o_begin, int64_t o_end) {
  for (int64_t a = s0, b; a < s1; a = b) {
    b = slab_end(a, s1);
    for (int64_t o0 = o_begin; o0 < o_end; o0 += OC) {
      small_weight_gradient_chunk<CO, OC, L, JB>(cols, n, ldc, s0, gy + o0, acc + o0 * kc, a, b);
    }
  }
}

// The levels the kernels are compiled for (the numbers of calibconv::ops::SmallKernelIsa).
enum class SmallIsa { None = 0, Avx2 = 1, Avx512 = 2 };

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define CALIBCONV_HAVE_SMALL_KERNELS 1
#define CALIBCONV_TARGET_V4 __attribute__((target("arch=x86-64-v4")))
#define CALIBCONV_TARGET_V3 __attribute__((target("arch=x86-64-v3")))

// One level's kernels for CO outputs in vectors of L floats: forward rows R and weight-gradient
// columns JB, both OC outputs at a time; column gradient CR rows x CJ vectors of CL floats.
#define CALIBCONV_SMALL_KERNELS(SUFFIX, TARGET, CO, L, R, JB, OC, CL, CR, CJ)                  \
  static_assert(OC == small_panel(CO), "a pass is one panel of the weight");                  \
  constexpr int64_t small_rows_##CO##_##SUFFIX = R;                                            \
  TARGET inline void small_forward_##CO##_##SUFFIX(                                            \
      const float* cols, int64_t n, int64_t ldc, int64_t kc, int64_t s0, int64_t s1,           \
      const float* wt, const float* bias, float* y) {                                          \
    small_forward_body<CO, L, R, OC>(cols, n, ldc, kc, s0, s1, wt, bias, y);                   \
  }                                                                                            \
  TARGET inline void small_column_gradient_##CO##_##SUFFIX(const float* gy, int64_t n,         \
                                                           int64_t kc, const float* w,         \
                                                           float* g) {                         \
    small_column_gradient_body<CO, CL, CR, CJ>(gy, n, kc, w, g);                               \
  }                                                                                            \
  TARGET inline void small_weight_gradient_##CO##_##SUFFIX(                                    \
      const float* cols, int64_t n, int64_t ldc, int64_t kc, int64_t s0, int64_t s1,           \
      const float* gy, float* acc, int64_t o0, int64_t o1) {                                   \
    small_weight_gradient_body<CO, L, JB, OC>(cols, n, ldc, kc, s0, s1, gy, acc, o0, o1);      \
  }
// (256 to 1024 outputs run as passes of 64, the weight in panels, large weights in blocks of
// SMALL_LARGE_BLOCK_ROWS and slabs: faster than the BLAS up to SMALL_MAX_WEIGHT.)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 8, 8, 8, 12, 8, 16, 4, 4)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 16, 16, 12, 12, 16, 16, 8, 3)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 32, 16, 12, 8, 32, 16, 8, 3)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 64, 16, 6, 6, 64, 16, 8, 3)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 128, 16, 6, 6, 64, 16, 8, 3)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 256, 16, 6, 6, 64, 16, 6, 4)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 512, 16, 6, 6, 64, 16, 6, 4)
CALIBCONV_SMALL_KERNELS(v4, CALIBCONV_TARGET_V4, 1024, 16, 6, 6, 64, 16, 6, 4)
CALIBCONV_SMALL_KERNELS(v3, CALIBCONV_TARGET_V3, 8, 8, 8, 8, 8, 8, 4, 3)
CALIBCONV_SMALL_KERNELS(v3, CALIBCONV_TARGET_V3, 16, 8, 6, 4, 16, 8, 4, 3)
CALIBCONV_SMALL_KERNELS(v3, CALIBCONV_TARGET_V3, 32, 8, 2, 2, 32, 8, 4, 3)
// (AVX2 has none for 64 and 128 outputs: as passes of 32 they lost to the BLAS.)
#undef CALIBCONV_SMALL_KERNELS
#endif

// The highest level this CPU runs, capped by the last calibconv_native_small_isa call (tests run
// the AVX2 kernels on an AVX-512 machine with it).
inline std::atomic<int> small_isa_cap{static_cast<int>(SmallIsa::Avx512)};

inline SmallIsa small_isa() {
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
  static const SmallIsa cpu = [] {
    __builtin_cpu_init();
    if (__builtin_cpu_supports("x86-64-v4")) return SmallIsa::Avx512;
    if (__builtin_cpu_supports("x86-64-v3")) return SmallIsa::Avx2;
    return SmallIsa::None;
  }();
  return static_cast<SmallIsa>(std::min(static_cast<int>(cpu), small_isa_cap.load()));
#else
  return SmallIsa::None;
#endif
}

// The few-output-channel kernels of a pass, or all null where they do not apply (another channel
// count, a CPU without AVX2). column_gradient also needs kc % 8 == 0.
struct SmallKernels {
  // forward(cols, n, ldc, kc, s0, s1, wt, bias, y): the reduction range [s0, s1) of kc, whose
  // columns cols holds at row stride ldc (see small_forward_body).
  void (*forward)(const float*, int64_t, int64_t, int64_t, int64_t, int64_t, const float*,
                  const float*, float*) = nullptr;
  void (*column_gradient)(const float*, int64_t, int64_t, const float*, float*) = nullptr;
  // weight_gradient(cols, n, ldc, kc, s0, s1, gy, acc, o0, o1): the columns [s0, s1) of kc, as
  // forward, for the outputs [o0, o1) (whole panels: multiples of small_panel(C_out)).
  void (*weight_gradient)(const float*, int64_t, int64_t, int64_t, int64_t, int64_t, const float*,
                          float*, int64_t, int64_t) = nullptr;
  // The forward's rows at a time (R): a block of a multiple of it multiplies no row alone.
  int64_t rows = 1;
  explicit operator bool() const { return forward != nullptr; }
};

// The largest weight (K*C x C_out values) the kernels take: 9 Mi values, 36 MiB, the largest
// measured (1024->1024, 3x3), faster through them than through the BLAS; see the 256- to
// 1024-output kernels above. Larger weights go through the BLAS, untimed.
constexpr int64_t SMALL_MAX_WEIGHT = 9 << 20;

// The kernels for C_out outputs and K*C = kc columns (float32, one group) at the level in use.
inline SmallKernels small_kernels_for(int64_t cout, int64_t kc) {
  SmallKernels s;
  if (kc * cout > SMALL_MAX_WEIGHT) return s;
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
  const SmallIsa isa = small_isa();
#define CALIBCONV_SMALL_PICK(CO, SUFFIX)                       \
  case CO:                                                     \
    s.forward = small_forward_##CO##_##SUFFIX;                 \
    s.column_gradient = small_column_gradient_##CO##_##SUFFIX; \
    s.weight_gradient = small_weight_gradient_##CO##_##SUFFIX; \
    s.rows = small_rows_##CO##_##SUFFIX;                       \
    break;
  if (isa == SmallIsa::Avx512) {
    switch (cout) {
      CALIBCONV_SMALL_PICK(8, v4)
      CALIBCONV_SMALL_PICK(16, v4)
      CALIBCONV_SMALL_PICK(32, v4)
      CALIBCONV_SMALL_PICK(64, v4)
      CALIBCONV_SMALL_PICK(128, v4)
      CALIBCONV_SMALL_PICK(256, v4)
      CALIBCONV_SMALL_PICK(512, v4)
      CALIBCONV_SMALL_PICK(1024, v4)
      default:
        return s;
    }
  } else if (isa == SmallIsa::Avx2) {
    switch (cout) {
      CALIBCONV_SMALL_PICK(8, v3)
      CALIBCONV_SMALL_PICK(16, v3)
      CALIBCONV_SMALL_PICK(32, v3)
      default:
        return s;
    }
  }
#undef CALIBCONV_SMALL_PICK
#endif
  if (kc % 8 != 0) s.column_gradient = nullptr;
  return s;
}

}  // namespace calibconv::native
