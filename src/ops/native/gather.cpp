// The gather and scatter kernels of calibconv's native deformable convolution: the columns of
// output pixels from the padded input, and the column gradient added back to the corners the
// samples read; compiled per (element type, channel count) and instruction set. What was measured
// for the choices below: docs/bench/cpu-kernels.md.

#include "gather.h"

#include <algorithm>
#include <type_traits>

namespace calibconv::native {

// The gather of the columns of output pixels [p0, p0 + n) of batch item b into cols [n, K*C]
// (layout: group, tap, channel within the group) from the padded channels-last input xp
// (padded_input): a sample's corners are t, t + 1, t + Wp, t + Wp + 1 from its top-left corner t
// (the plan's top_left; ops/plan/mod.rs says why every corner, inside or not, is a real pixel of
// the padded input), each weighted by its bilinear weight: one index load per sample, no selects.
// This replaced a gather through the plan's four corner indices into the unpadded input, each with
// a select for out-of-range corners: the same bits, in less time.
// NC > 0 fixes the channel count at compile time (one group): at 3-64 channels a sample is a few
// vector operations, so the channel loop must be unrolled and vectorised for the instruction set
// (the callers below are multiversioned; this body is inlined into every clone). Three channels
// (a first layer's RGB) go through vectors of four: each corner load also reads the next pixel's
// first channel (the padded input ends with slack for it), and each sample's store writes one
// value past its row, which the next sample's store overwrites; the call's last sample stores its
// three values alone (the values after it belong to another call, maybe another thread's).
template <typename T, int NC>
constexpr int gather_lanes() {
  constexpr int L = NC == 3 ? 4 : NC;
  if constexpr (NC >= 3 && VecOf<T, L>::ok) return L;
  return 0;
}

// Lanes of the vectors that the gather and the scatter of NC channels compute with: NC (4 for
// 3), at most 32 bytes. Wider channel vectors go in chunks of 32 bytes: GCC 12 lowers a store
// of a vector wider than the clone's registers, inside these loops, through the stack (spills,
// general-register moves, four 16-byte stores that read back across two 32-byte writes, a
// store-forwarding stall); in 32-byte chunks it is two plain stores (the same values: each lane
// is the same expression), and faster.
template <typename T, int NC>
constexpr int chunk_lanes() {
  constexpr int L = NC == 3 ? 4 : NC, most = static_cast<int>(32 / sizeof(T));
  return L < most ? L : most;
}

// Sample i's value: its four corners (from its top-left corner a, `down` values a padded row),
// weighted and summed (one expression for the samples stored whole and the call's last sample of
// 3 channels, stored value by value; an always-inlined template takes its caller's clone's
// instruction set).
template <typename V, typename T, int NC>
CALIBCONV_ALWAYS_INLINE inline V gather_sample(const T* xb, const int32_t* tl, const T* coef,
                                               int64_t down, int64_t i, int c0) {
  const Corners<T> w = corners_at<T, NC>(coef, i);
  const T* a = xb + int64_t{tl[i]} * NC + c0;
  return w.w0 * load<V>(a) + w.w1 * load<V>(a + NC) + w.w2 * load<V>(a + down) +
         w.w3 * load<V>(a + down + NC);
}

// The samples [0, i) of a 3-channel float gather, four at a time, returned i (the rest, at least
// one sample, goes one at a time: see gather_columns_body). Two samples share a vector of eight
// floats (each in four lanes, as one sample's vector of four in the loop one at a time), so
// every weight, product and sum is computed once for two samples; the bilinear weights of four
// samples come from one load of their fractions, spread to the lanes by a shuffle. Each lane
// computes the same expression of the same values as the loop one at a time (the same bits).
// A pair's six values are packed and stored as eight: the last two land on the next sample's
// first values, which this call stores later (hence i + 4 < count). Faster than the loop one at a
// time where the columns stay in L1; where they are kept (written to memory), the stores bound it.
CALIBCONV_ALWAYS_INLINE inline int64_t gather3_quads(const float* xb, const int32_t* tl,
                                                    const float* f, int64_t down, int64_t count,
                                                    float* cols) {
  using V8 = VecOf<float, 8>::type;
  using V4 = VecOf<float, 4>::type;
  using I8 = VecOf<int32_t, 8>::type;
  constexpr int NC = 3;
  int64_t i = 0;
  static_assert(!reads_corner_weights(NC));
  for (; i + 4 < count; i += 4) {
    const V8 fr = load<V8>(f + 2 * i);
    for (int h = 0; h < 2; ++h) {
      const int64_t s = i + 2 * h;
      const V8 ly = h == 0 ? __builtin_shuffle(fr, I8{0, 0, 0, 0, 2, 2, 2, 2})
                           : __builtin_shuffle(fr, I8{4, 4, 4, 4, 6, 6, 6, 6});
      const V8 lx = h == 0 ? __builtin_shuffle(fr, I8{1, 1, 1, 1, 3, 3, 3, 3})
                           : __builtin_shuffle(fr, I8{5, 5, 5, 5, 7, 7, 7, 7});
      const V8 hy = 1 - ly, hx = 1 - lx;
      const float* a0 = xb + int64_t{tl[s]} * NC;
      const float* a1 = xb + int64_t{tl[s + 1]} * NC;
      const auto both = [&](int64_t o) {
        return __builtin_shufflevector(load<V4>(a0 + o), load<V4>(a1 + o), 0, 1, 2, 3, 4, 5, 6, 7);
      };
      const V8 v = (hy * hx) * both(0) + (hy * lx) * both(NC) + (ly * hx) * both(down) +
                   (ly * lx) * both(down + NC);
      store(cols + s * NC, __builtin_shuffle(v, I8{0, 1, 2, 4, 5, 6, 7, 7}));
    }
  }
  return i;
}

// A sample's bilinear weights and its four corners (from its top-left corner tl[i], C values a
// pixel, `down` values a padded row), and its values of n channels from channel o on: the
// expression of every gather of one channel at a time (the vectorised paths compute the same
// expression on vectors).
template <typename T>
struct Sample {
  T w0, w1, w2, w3;
  const T *a0, *a1, *a2, *a3;
};
template <typename T, int NC>
CALIBCONV_ALWAYS_INLINE inline Sample<T> sample_at(const T* xb, const int32_t* tl, const T* coef,
                                                   int64_t i, int64_t C, int64_t down) {
  const Corners<T> w = corners_at<T, NC>(coef, i);
  const T* a0 = xb + int64_t{tl[i]} * C;
  return {w.w0, w.w1, w.w2, w.w3, a0, a0 + C, a0 + down, a0 + down + C};
}
template <typename T>
CALIBCONV_ALWAYS_INLINE inline void sample_channels(const Sample<T>& s, int64_t o, int64_t n,
                                                    T* __restrict dst) {
  const T *__restrict a0 = s.a0 + o, *__restrict a1 = s.a1 + o, *__restrict a2 = s.a2 + o,
                     *__restrict a3 = s.a3 + o;
  CALIBCONV_IVDEP
  for (int64_t c = 0; c < n; ++c) {
    dst[c] = s.w0 * a0[c] + s.w1 * a1[c] + s.w2 * a2[c] + s.w3 * a3[c];
  }
}

// Whether the gather and scatter of NC channels in chunks of CLW lanes compute the samples'
// bilinear weights first, WEIGHT_CHUNK samples at a time into an L1 buffer (corner_weights), and
// then read each weight from there as a broadcast operand: the 64-byte variants of 16 float
// channels and more (AVX-512, tile_kernels). Computed per sample, the weights are six scalar
// operations and four broadcasts from registers, and with 512-bit operations in flight (which leave
// the vector units of two ports to them) those ten take the ports that the sample's four
// multiply-adds need; from memory a broadcast is a load. Each weight is the same expression (the
// same bits).
constexpr int64_t WEIGHT_CHUNK = 64;
template <typename T, int NC, int CLW>
constexpr bool weights_first() {
  return std::is_same_v<T, float> && NC >= 16 && CLW == 16 && !reads_corner_weights(NC);
}

// The four bilinear weights of samples [0, m) (m <= WEIGHT_CHUNK) from their fractions f (two a
// sample), into w[c * WEIGHT_CHUNK + i] for corner c: corners_at's expressions, sixteen samples
// a vector (the fractions de-interleaved by a shuffle), the rest one at a time.
CALIBCONV_ALWAYS_INLINE inline void corner_weights(const float* __restrict f, int64_t m,
                                                   float* __restrict w) {
  using V = VecOf<float, 16>::type;
  using I = VecOf<int32_t, 16>::type;
  int64_t i = 0;
  for (; i + 16 <= m; i += 16) {
    const V a = load<V>(f + 2 * i), b = load<V>(f + 2 * i + 16);
    constexpr I even{0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30};
    const V ly = __builtin_shuffle(a, b, even), lx = __builtin_shuffle(a, b, even + 1);
    const V hy = 1 - ly, hx = 1 - lx;
    store(w + i, hy * hx);
    store(w + WEIGHT_CHUNK + i, hy * lx);
    store(w + 2 * WEIGHT_CHUNK + i, ly * hx);
    store(w + 3 * WEIGHT_CHUNK + i, ly * lx);
  }
  for (; i < m; ++i) {
    const Corners<float> c = corners_at<float, 16>(f, i);
    w[i] = c.w0;
    w[WEIGHT_CHUNK + i] = c.w1;
    w[2 * WEIGHT_CHUNK + i] = c.w2;
    w[3 * WEIGHT_CHUNK + i] = c.w3;
  }
}

template <typename T, int NC, int CLW = chunk_lanes<T, NC>()>
CALIBCONV_ALWAYS_INLINE inline void gather_columns_body(const Geo& g, const T* xp,
                                                        const int32_t* top_left, const T* coef,
                                                        int64_t b, int64_t p0, int64_t n,
                                                        T* cols) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;  // per-item plans index the stacked padded items
  const int64_t C = NC > 0 ? NC : g.C, Cg = NC > 0 ? NC : g.Cg, G = NC > 0 ? 1 : g.G;
  const int64_t K = g.K, down = g.Wp * C;
  const T* xb = xp + (b * frame - shift) * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const T* __restrict f = coef + coef_stride(NC) * s_begin;
  if constexpr (NC > 0 && gather_lanes<T, NC>() > 0) {
    // One group: the columns are the samples' rows back to back.
    constexpr int L = gather_lanes<T, NC>(), CL = CLW;
    using V = typename VecOf<T, CL>::type;
    const int64_t count = n * K;
    // (NC < L) the call's last sample stores its NC values alone, below.
    const int64_t whole = NC < L ? count - 1 : count;
    int64_t first = 0;
    if constexpr (NC == 3 && std::is_same_v<T, float>) {
      first = gather3_quads(xb, tl, f, down, count, cols);
    }
    if constexpr (weights_first<T, NC, CL>()) {
      alignas(64) float w[4 * WEIGHT_CHUNK];
      for (int64_t i0 = 0; i0 < count; i0 += WEIGHT_CHUNK) {
        const int64_t m = std::min(WEIGHT_CHUNK, count - i0);
        corner_weights(f + 2 * i0, m, w);
        for (int64_t j = 0; j < m; ++j) {
          const int64_t i = i0 + j;
          const T* a = xb + int64_t{tl[i]} * NC;
          for (int c0 = 0; c0 < L; c0 += CL) {
            const T* ac = a + c0;
            store(cols + i * NC + c0,
                  w[j] * load<V>(ac) + w[WEIGHT_CHUNK + j] * load<V>(ac + NC) +
                      w[2 * WEIGHT_CHUNK + j] * load<V>(ac + down) +
                      w[3 * WEIGHT_CHUNK + j] * load<V>(ac + down + NC));
          }
        }
      }
      return;
    }
    for (int64_t i = first; i < whole; ++i) {
      if constexpr (L == CL) {
        store(cols + i * NC, gather_sample<V, T, NC>(xb, tl, f, down, i, 0));
      } else {
        // Several chunks (16 to 64 channels): the weights once per sample. Written per chunk,
        // GCC recomputed them for every chunk (seen in the disassembly of the AVX-512
        // clone), which was slower; the same bits.
        const auto [w0, w1, w2, w3] = corners_at<T, NC>(f, i);
        const T* a = xb + int64_t{tl[i]} * NC;
        for (int c0 = 0; c0 < L; c0 += CL) {
          const T* ac = a + c0;
          store(cols + i * NC + c0, w0 * load<V>(ac) + w1 * load<V>(ac + NC) +
                                        w2 * load<V>(ac + down) + w3 * load<V>(ac + down + NC));
        }
      }
    }
    if (whole < count && count > 0) {  // NC = 3: one chunk
      const V v = gather_sample<V, T, NC>(xb, tl, f, down, whole, 0);
      for (int c = 0; c < NC; ++c) cols[whole * NC + c] = v[c];
    }
    return;
  }
  const int64_t row = K * C;
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = 0; k < K; ++k) {
      const Sample<T> sm = sample_at<T, NC>(xb, tl, f, t * K + k, C, down);
      T* dst = cols + t * row + k * Cg;
      if constexpr (NC > 0) {
        sample_channels(sm, 0, NC, dst);
      } else {
        for (int64_t gi = 0; gi < G; ++gi) sample_channels(sm, gi * Cg, Cg, dst + gi * K * Cg);
      }
    }
  }
}

// The columns [s0, s1) of the rows of output pixels [p0, p0 + n) of batch item b (one group),
// into cols [n, s1 - s0] at row stride ldc: for the few-output-channel kernels' large weights,
// whose forward gathers and multiplies a block's columns one slab at a time (forward_impl). Each
// value is gather_columns_body's expression (the same bits). coef: fractions (such layers have
// more than CORNER_WEIGHTS_MAX_C channels: a weight of SMALL_LARGE_WEIGHT values at 8 channels
// would need over 3000 outputs).
CALIBCONV_CLONES void gather_range_float(const Geo& g, const float* xp, const int32_t* top_left,
                                         const float* frac, int64_t b, int64_t p0, int64_t n,
                                         int64_t s0, int64_t s1, float* cols, int64_t ldc) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;  // per-item plans index the stacked padded items
  const int64_t C = g.C, K = g.K, down = g.Wp * C;
  const float* xb = xp + (b * frame - shift) * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const float* __restrict f = frac + 2 * s_begin;
  const int64_t k0 = s0 / C, k1 = (s1 + C - 1) / C;  // the taps the range covers
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = k0; k < k1; ++k) {
      const Sample<float> sm = sample_at<float, 0>(xb, tl, f, t * K + k, C, down);
      // (the channels [c0, c1) of tap k; channel c of the tap is column k * C + c)
      const int64_t c0 = std::max<int64_t>(s0 - k * C, 0), c1 = std::min<int64_t>(s1 - k * C, C);
      sample_channels(sm, c0, c1 - c0, cols + t * ldc + (k * C + c0 - s0));
    }
  }
}

// Adds the column-gradient tile gcols [n, K*C] (layout as the columns) of output pixels
// [p0, p0 + n) of batch item b to the corners they sampled, in the padded channels-last rows gxp
// (as padded_input; GradientRows holds them and writes them out). Corners off the input add into
// the padding; samples wholly outside (the plan's zero block) are skipped, so no two tasks of a
// phase write the same padding pixel. Every pixel of the input gets the same additions in the same
// order as in the scatter into the unpadded input that came before (which skipped out-of-range
// corners), the same bits (with Border::WrapX the first column's additions through the right
// padding column come last), in less time.
// A corner of zero weight adds w * g = +-0, which leaves every value but -0 as it is, and no
// value here is -0 (the buffer starts at +0, and a sum is -0 only if both terms are): the same
// bits as skipping it, for every finite gradient (an infinite or NaN one spreads NaN to its
// zero-weight corners too). Such corners lie in the rows the plan's `rows` name (floor(y) and
// floor(y) + 1 of every sample), so the bands stay disjoint. The branch that skipped them cost
// more than the additions: two taken jumps a corner.
// NC as in gather_columns_body.
template <typename T, int NC, int CLW = chunk_lanes<T, NC>()>
CALIBCONV_ALWAYS_INLINE inline void scatter_columns_body(const Geo& g, T* gxp,
                                                         const int32_t* top_left, const T* coef,
                                                         int64_t b, int64_t p0, int64_t n,
                                                         const T* gcols) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;
  const int64_t C = NC > 0 ? NC : g.C, Cg = NC > 0 ? NC : g.Cg, G = NC > 0 ? 1 : g.G;
  const int64_t K = g.K, down = g.Wp * C;
  const int64_t blank = shift + (g.H + 1) * g.Wp;
  T* gxb = gxp + (b * frame - shift) * C;
  const int64_t row = K * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const T* __restrict f = coef + coef_stride(NC) * s_begin;
  const int64_t corner[4] = {0, C, down, down + C};
  if constexpr (weights_first<T, NC, CLW>()) {  // one group: sample i's columns at i * NC
    using V = typename VecOf<T, CLW>::type;
    alignas(64) float w[4 * WEIGHT_CHUNK];
    const int64_t count = n * K;
    for (int64_t i0 = 0; i0 < count; i0 += WEIGHT_CHUNK) {
      const int64_t m = std::min(WEIGHT_CHUNK, count - i0);
      corner_weights(f + 2 * i0, m, w);
      for (int64_t j = 0; j < m; ++j) {
        const int64_t i = i0 + j;
        if (tl[i] == blank) continue;
        const T* __restrict src = gcols + i * NC;
        T* const a = gxb + int64_t{tl[i]} * C;
        for (int c = 0; c < 4; ++c) {
          T* __restrict dst = a + corner[c];
          const T wc = w[c * WEIGHT_CHUNK + j];
          for (int c0 = 0; c0 < NC; c0 += CLW) {
            store(dst + c0, load<V>(dst + c0) + wc * load<V>(src + c0));
          }
        }
      }
    }
    return;
  }
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = 0; k < K; ++k) {
      const int64_t i = t * K + k;
      if (tl[i] == blank) continue;
      const Corners<T> cw = corners_at<T, NC>(f, i);
      const T w[4] = {cw.w0, cw.w1, cw.w2, cw.w3};
      const T* __restrict src = gcols + t * row + k * Cg;
      T* const a = gxb + int64_t{tl[i]} * C;
      for (int c = 0; c < 4; ++c) {
        T* __restrict dst = a + corner[c];
        const T wc = w[c];
        if constexpr (NC > 0 && VecOf<T, NC>::ok) {
          constexpr int CL = CLW;
          using V = typename VecOf<T, CL>::type;
          for (int c0 = 0; c0 < NC; c0 += CL) {
            store(dst + c0, load<V>(dst + c0) + wc * load<V>(src + c0));
          }
        } else if constexpr (NC > 0) {
          for (int j = 0; j < NC; ++j) dst[j] += wc * src[j];
        } else {
          for (int64_t gi = 0; gi < G; ++gi) {
            T* __restrict d = dst + gi * Cg;
            const T* __restrict q = src + gi * K * Cg;
            CALIBCONV_IVDEP
            for (int64_t j = 0; j < Cg; ++j) d[j] += wc * q[j];
          }
        }
      }
    }
  }
}

// The multiversioned entry points, one per (element type, fixed channel count): NC = 0 is the
// general case (any channels, any groups). CALIBCONV_TILE_KERNELS_AS names them
// gather_T_NC<SUFFIX> / scatter_T_NC<SUFFIX>, compiled with ATTR and chunks of CLW lanes
// (CALIBCONV_SCATTER_AS: the scatter alone).
#define CALIBCONV_SCATTER_AS(ATTR, T, NC, SUFFIX, CLW)                                          \
  ATTR void scatter_##T##_##NC##SUFFIX(const Geo& g, T* gxp, const int32_t* top_left,         \
                                       const T* coef, int64_t b, int64_t p0, int64_t n,        \
                                       const T* gcols) {                                       \
    scatter_columns_body<T, NC, CLW>(g, gxp, top_left, coef, b, p0, n, gcols);                 \
  }
#define CALIBCONV_TILE_KERNELS_AS(ATTR, T, NC, SUFFIX, CLW)                                     \
  ATTR void gather_##T##_##NC##SUFFIX(const Geo& g, const T* xp, const int32_t* top_left,     \
                                      const T* coef, int64_t b, int64_t p0, int64_t n,         \
                                      T* cols) {                                               \
    gather_columns_body<T, NC, CLW>(g, xp, top_left, coef, b, p0, n, cols);                    \
  }                                                                                            \
  CALIBCONV_SCATTER_AS(ATTR, T, NC, SUFFIX, CLW)
#define CALIBCONV_TILE_KERNELS(T, NC) \
  CALIBCONV_TILE_KERNELS_AS(CALIBCONV_CLONES, T, NC, , (chunk_lanes<T, NC>()))
#define CALIBCONV_TILE_KERNELS_ALL(T) \
  CALIBCONV_TILE_KERNELS(T, 0)        \
  CALIBCONV_TILE_KERNELS(T, 1)        \
  CALIBCONV_TILE_KERNELS(T, 2)        \
  CALIBCONV_TILE_KERNELS(T, 3)        \
  CALIBCONV_TILE_KERNELS(T, 4)        \
  CALIBCONV_TILE_KERNELS(T, 8)        \
  CALIBCONV_TILE_KERNELS(T, 16)       \
  CALIBCONV_TILE_KERNELS(T, 32)       \
  CALIBCONV_TILE_KERNELS(T, 64)
CALIBCONV_TILE_KERNELS_ALL(float)
CALIBCONV_TILE_KERNELS_ALL(double)

// The gather and scatter of 16, 32, 64, 128 and 256 float channels in whole 64-byte vectors, each
// chunk of samples' bilinear weights computed first (weights_first), compiled for AVX-512 only
// (x86-64-v4, as the few-output-channel kernels: in the multiversioned bodies above GCC would lower
// such vectors through the stack in the AVX2 clone) and picked where the CPU has it (tile_kernels).
// Each lane computes the same expression as the 32-byte chunks and the general loop (the same bits,
// which few_output_channel_kernels_agree_across_isa_levels checks). Faster than the 32-byte chunks
// on an Intel Xeon with AVX-512 (the 16-channel gather only with the weights computed first).
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 32, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 64, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 128, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 256, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 16, _v4, 16)
#endif

#define CALIBCONV_PICK_AS(T, NC, SUFFIX) \
  case NC:                               \
    return {gather_##T##_##NC##SUFFIX, scatter_##T##_##NC##SUFFIX, NC};
#define CALIBCONV_PICK(T, NC) CALIBCONV_PICK_AS(T, NC, )
#define CALIBCONV_PICK_ALL(T)                                 \
  switch (g.G == 1 ? g.C : 0) {                               \
    CALIBCONV_PICK(T, 1)                                      \
    CALIBCONV_PICK(T, 2)                                      \
    CALIBCONV_PICK(T, 3)                                      \
    CALIBCONV_PICK(T, 4)                                      \
    CALIBCONV_PICK(T, 8)                                      \
    CALIBCONV_PICK(T, 16)                                     \
    CALIBCONV_PICK(T, 32)                                     \
    CALIBCONV_PICK(T, 64)                                     \
    default:                                                  \
      return {gather_##T##_0, scatter_##T##_0, 0};            \
  }

template <>
TileKernels<float> tile_kernels<float>(const Geo& g) {
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
  if (g.G == 1 && small_isa() == SmallIsa::Avx512) {
    switch (g.C) {
      CALIBCONV_PICK_AS(float, 32, _v4)
      CALIBCONV_PICK_AS(float, 64, _v4)
      CALIBCONV_PICK_AS(float, 128, _v4)
      CALIBCONV_PICK_AS(float, 256, _v4)
      CALIBCONV_PICK_AS(float, 16, _v4)
      default:
        break;
    }
  }
#endif
  CALIBCONV_PICK_ALL(float)
}
template <>
TileKernels<double> tile_kernels<double>(const Geo& g) {
  CALIBCONV_PICK_ALL(double)
}

// Batch item J's lanes of a vector of four items (batch_gather, see gather.h).
template <int J>
CALIBCONV_ALWAYS_INLINE inline VecOf<float, 4>::type item_lanes(const VecOf<float, 16>::type& v) {
  return __builtin_shufflevector(v, v, 4 * J, 4 * J + 1, 4 * J + 2, 4 * J + 3);
}
CALIBCONV_CLONES void batch_gather(const Geo& g, const float* xq, const int32_t* top_left,
                                   const float* coef, int64_t p0, int64_t n, float* cols,
                                   int64_t ldb) {
  using V16 = VecOf<float, 16>::type;
  using V4 = VecOf<float, 4>::type;
  constexpr int NC = 3;
  const int64_t K = g.K, B = g.B, pix = batch_items(B) * 4, down = g.Wp * pix;
  const int32_t* __restrict tl = top_left + p0 * K;
  const float* __restrict f = coef + coef_stride(NC) * p0 * K;
  const int64_t count = n * K;
  for (int64_t i = 0; i < count; ++i) {
    const auto [w0, w1, w2, w3] = corners_at<float, NC>(f, i);
    const float* a = xq + int64_t{tl[i]} * pix;
    const bool last = i + 1 == count;
    for (int64_t b0 = 0; b0 < B; b0 += 4) {
      const float* ab = a + b0 * 4;
      const V16 v = w0 * load<V16>(ab) + w1 * load<V16>(ab + pix) + w2 * load<V16>(ab + down) +
                    w3 * load<V16>(ab + down + pix);
      const auto put = [&](int64_t b, const V4& u) CALIBCONV_ALWAYS_INLINE {
        float* d = cols + b * ldb + i * NC;
        if (!last) {
          store(d, u);
        } else {
          for (int c = 0; c < NC; ++c) d[c] = u[c];
        }
      };
      put(b0, item_lanes<0>(v));
      if (b0 + 1 < B) put(b0 + 1, item_lanes<1>(v));
      if (b0 + 2 < B) put(b0 + 2, item_lanes<2>(v));
      if (b0 + 3 < B) put(b0 + 3, item_lanes<3>(v));
    }
  }
}

// gather_rows for the columns [s0, s1) (gather_range_float), into cols at row stride ldc.
void gather_range_rows(const Geo& g, PaddedRows<float>& src, const int32_t* top_left,
                       const float* coef, int64_t q0, int64_t n, int64_t s0, int64_t s1,
                       float* cols, int64_t ldc) {
  for_items(g.P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
    gather_range_float(g, src.piece(b, p0, len), top_left, coef, b, p0, len, s0, s1,
                       cols + off * ldc, ldc);
  });
}

at::Tensor sample_coefficients(const at::Tensor& frac, const Geo& g) {
  const int64_t nc = frac.scalar_type() == at::kFloat ? tile_kernels<float>(g).nc
                                                      : tile_kernels<double>(g).nc;
  if (!reads_corner_weights(nc)) return frac;
  const at::Tensor f = frac.contiguous();
  const int64_t n = f.numel() / 2;
  at::Tensor w = at::empty({n * 4}, f.options());
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "calibconv_corner_weights", [&] {
    const scalar_t* __restrict src = f.const_data_ptr<scalar_t>();
    scalar_t* __restrict dst = w.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, n, 4096, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const Corners<scalar_t> c = corners_at<scalar_t, 0>(src, i);  // (from fractions)
        dst[4 * i] = c.w0;
        dst[4 * i + 1] = c.w1;
        dst[4 * i + 2] = c.w2;
        dst[4 * i + 3] = c.w3;
      }
    });
  });
  return w;
}

}  // namespace calibconv::native
