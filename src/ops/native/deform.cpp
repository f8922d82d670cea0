// Native CPU kernels of calibconv's deformable convolution with fixed offsets, as a
// torch::autograd::Function called from Rust (src/ops/native/mod.rs). The design and its
// numerics are documented in src/ops/mod.rs; in short, with K taps, C input and C_out output
// channels, G groups, and P output pixels:
//
// - The weight is packed per pass as WP [G, C_out/G, K, C/G] (the tap and channel axes of every
//   output channel swapped, a cheap local transpose); the backward pass repacks it rather than
//   keeping a weight-sized buffer alive between the passes.
// - forward: per tile of T output pixels, gather the column tile [T, K*C] (layout: group, tap,
//   channel) from a channels-last view of the input with the plan's four corner indices and the
//   bilinear weights of its fractions (ly, lx), then one GEMM per group,
//   out[T, C_out/G] = cols_g @ WP_g^T, written in place into the output (NCHW or channels-last,
//   as the input), bias preloaded.
// - backward, weight: the column tiles are recomputed (never stored) and
//   acc_g[C_out/G, K*C/G] += gy_g^T @ cols_g, one accumulator per thread chunk, summed at the end.
// - backward, input: per tile, grad_cols_g = gy_g @ WP_g, then every sample adds w * grad_cols
//   to its four corners of a channels-last gradient buffer (a scatter). Tiles run in bands of
//   output rows, in two phases (even bands, then odd bands) chosen so that the input rows that
//   two bands of the same phase touch are disjoint: no atomics, no races, and the summation order
//   does not depend on the number of threads.
// - bias: a sum of the output gradient.
//
// Tiles run in parallel with at::parallel_for. The entry point catches every C++ exception and
// returns its message: no exception crosses into Rust.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/csrc/autograd/custom_function.h>

#include <algorithm>
#include <atomic>
#include <climits>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// ---------------------------------------------------------------------------------------------
// Tiling.

// Bytes of a gathered tile: the tile stays in the last-level cache and every GEMM is large
// enough to amortise packing the weight, which the BLAS does per call. A weight larger than
// TILE_BYTES per thread raises the budget to its share per thread (the GEMM then spends on the
// tile at least as much as on packing the weight).
constexpr int64_t TILE_BYTES = 2 << 20;
// Rows of a tile: at least MIN_TILE (GEMM efficiency), at most MAX_TILE.
constexpr int64_t MIN_TILE = 128;
constexpr int64_t MAX_TILE = 4096;

// Rows per tile for `rows` rows per batch item of `row_elems` elements each, with a weight of
// `weight_elems` elements. Tiles never span items; small problems get one tile per thread
// (every tile repacks the weight, so splitting further only adds packing).
int64_t tile_rows(int64_t batch, int64_t rows, int64_t row_elems, int64_t weight_elems,
                  int64_t elem_bytes) {
  const int64_t threads = at::get_num_threads();
  const int64_t budget = std::max<int64_t>(TILE_BYTES, weight_elems * elem_bytes / threads);
  int64_t t = budget / std::max<int64_t>(1, row_elems * elem_bytes);
  t = std::clamp<int64_t>(t - t % 16, MIN_TILE, MAX_TILE);
  t = std::min(t, (batch * rows + threads - 1) / threads);
  return std::clamp<int64_t>(t, 1, std::max<int64_t>(1, rows));
}

// ---------------------------------------------------------------------------------------------
// Inner loops, written once per element type (not as templates) so that they can be compiled for
// several instruction sets and picked at load time (GCC/Clang function multiversioning).

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define CALIBCONV_CLONES \
  __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CALIBCONV_CLONES
#endif

// dst[i] = w0 a0[i] + w1 a1[i] + w2 a2[i] + w3 a3[i]
#define CALIBCONV_BLEND4(T, NAME)                                                          \
  CALIBCONV_CLONES void NAME(T* __restrict dst, const T* __restrict a0,                    \
                             const T* __restrict a1, const T* __restrict a2,               \
                             const T* __restrict a3, T w0, T w1, T w2, T w3, int64_t n) {  \
    for (int64_t i = 0; i < n; ++i) {                                                      \
      dst[i] = w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i];                          \
    }                                                                                      \
  }
CALIBCONV_BLEND4(float, blend4_f32)
CALIBCONV_BLEND4(double, blend4_f64)

// dst[i] += w src[i]
#define CALIBCONV_AXPY(T, NAME)                                                              \
  CALIBCONV_CLONES void NAME(T* __restrict dst, const T* __restrict src, T w, int64_t n) { \
    for (int64_t i = 0; i < n; ++i) {                                                        \
      dst[i] += w * src[i];                                                                  \
    }                                                                                        \
  }
CALIBCONV_AXPY(float, axpy_f32)
CALIBCONV_AXPY(double, axpy_f64)

// Below this many channels the loops run inline: the multiversioned functions are reached
// through an indirect call, which costs more than a few multiply-adds (the first layer has 3).
constexpr int64_t INLINE_BELOW = 16;

inline void blend4(float* d, const float* a0, const float* a1, const float* a2, const float* a3,
                   float w0, float w1, float w2, float w3, int64_t n) {
  if (n < INLINE_BELOW) {
    for (int64_t i = 0; i < n; ++i) d[i] = w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i];
  } else {
    blend4_f32(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
  }
}
inline void blend4(double* d, const double* a0, const double* a1, const double* a2,
                   const double* a3, double w0, double w1, double w2, double w3, int64_t n) {
  if (n < INLINE_BELOW) {
    for (int64_t i = 0; i < n; ++i) d[i] = w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i];
  } else {
    blend4_f64(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
  }
}
inline void axpy(float* d, const float* s, float w, int64_t n) {
  if (n < INLINE_BELOW) {
    for (int64_t i = 0; i < n; ++i) d[i] += w * s[i];
  } else {
    axpy_f32(d, s, w, n);
  }
}
inline void axpy(double* d, const double* s, double w, int64_t n) {
  if (n < INLINE_BELOW) {
    for (int64_t i = 0; i < n; ++i) d[i] += w * s[i];
  } else {
    axpy_f64(d, s, w, n);
  }
}

// ---------------------------------------------------------------------------------------------
// GEMM on raw strided matrices through ATen (which calls the BLAS libtorch was built with; it
// runs single-threaded inside at::parallel_for).

// A matrix with element (i, j) at p[i * rs + j * cs]; one of rs, cs is 1.
template <typename T>
struct Mat {
  T* p;
  int64_t rows, cols, rs, cs;
  Mat<const T> as_const() const { return {p, rows, cols, rs, cs}; }
  Mat t() const { return {p, cols, rows, cs, rs}; }
};

template <typename T>
at::Tensor view_of(const Mat<T>& m) {
  using U = std::remove_const_t<T>;
  auto opts = at::TensorOptions().dtype(c10::CppTypeToScalarType<U>::value);
  return at::from_blob(const_cast<U*>(m.p), {m.rows, m.cols}, {m.rs, m.cs}, opts);
}

// c = a @ b (c is not read) or, with accumulate, c += a @ b.
template <typename T>
void gemm(const Mat<const T>& a, const Mat<const T>& b, const Mat<T>& c, bool accumulate) {
  auto tc = view_of(c);
  if (accumulate) {
    at::addmm_out(tc, tc, view_of(a), view_of(b));
  } else {
    at::mm_out(tc, view_of(a), view_of(b));
  }
}

// ---------------------------------------------------------------------------------------------
// Geometry and scheduling.

struct Geo {
  int64_t B, C, H, W, HW, Ho, Wo, P, K, G, Cg, Cout, Coutg;
  bool per_item;  // the plan holds one set of samples per batch item
  // Plan item of batch item b.
  int64_t item(int64_t b) const { return per_item ? b : 0; }
};

// input [B, C, H, W]; a weight [C_out, C/G, kh, kw] with kh * kw = K.
Geo geometry(const at::Tensor& input, int64_t cout, int64_t k, int64_t ho, int64_t wo,
             int64_t groups, bool per_item) {
  Geo g{};
  g.B = input.size(0);
  g.C = input.size(1);
  g.H = input.size(2);
  g.W = input.size(3);
  g.HW = g.H * g.W;
  g.Ho = ho;
  g.Wo = wo;
  g.P = ho * wo;
  g.K = k;
  g.G = groups;
  g.Cg = g.C / groups;
  g.Cout = cout;
  g.Coutg = g.Cout / groups;
  g.per_item = per_item;
  return g;
}

// Runs f(task, scratch) for task in [0, n) on the intra-op threads, handing tasks out
// dynamically (the machine may be shared: a slow thread does fewer tasks); every thread makes
// its scratch with init() once. Results must not depend on which thread runs a task.
template <typename Init, typename F>
void parallel_tasks(int64_t n, const Init& init, const F& f) {
  if (n <= 0) return;
  std::atomic<int64_t> next{0};
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), n));
  at::parallel_for(0, threads, 1, [&](int64_t, int64_t) {
    auto scratch = init();
    for (int64_t t = next++; t < n; t = next++) {
      f(t, scratch);
    }
  });
}

// Per-thread buffers: a tile and a zero vector for out-of-range corners.
template <typename T>
struct Scratch {
  std::vector<T> tile, zero;
};

// Output matrix of group gi for output pixels [p0, p0 + n) of item b: [n, C_out/G], in the
// output's layout (channels-last rows, or NCHW columns).
template <typename T>
Mat<T> out_block(const Geo& g, T* out, bool cl, int64_t b, int64_t gi, int64_t p0, int64_t n) {
  return cl ? Mat<T>{out + (b * g.P + p0) * g.Cout + gi * g.Coutg, n, g.Coutg, g.Cout, 1}
            : Mat<T>{out + (b * g.Cout + gi * g.Coutg) * g.P + p0, n, g.Coutg, 1, g.P};
}

// The bilinear weights of the four corners of a sample with fractional position (ly, lx):
// (1-ly)(1-lx), (1-ly)lx, ly(1-lx), ly lx, as torchvision (corners outside the input read the
// plan's zero row, so their weight does not matter).
template <typename T>
struct Weights {
  T w[4];
  explicit Weights(const T* frac) {
    const T ly = frac[0], lx = frac[1], hy = 1 - ly, hx = 1 - lx;
    w[0] = hy * hx;
    w[1] = hy * lx;
    w[2] = ly * hx;
    w[3] = ly * lx;
  }
  T operator[](int c) const { return w[c]; }
};

// Gathers the column tile of output pixels [p0, p0 + n) of batch item b into cols [n, K*C]
// (layout: group, tap, channel within the group) from the channels-last input x. NC > 0 fixes
// the channel count at compile time (one group): the first layer has 3 channels, where the
// per-sample work is all overhead unless the channel loop is unrolled.
template <typename T, int NC>
void gather_columns_impl(const Geo& g, const T* x, const int32_t* index, const T* frac,
                         const T* zero, int64_t b, int64_t p0, int64_t n, T* cols) {
  const int64_t item = g.item(b);
  const int64_t shift = item * (g.HW + 1);  // per-item plans index a stacked table
  const int64_t C = NC > 0 ? NC : g.C, Cg = NC > 0 ? NC : g.Cg, G = NC > 0 ? 1 : g.G;
  const T* xb = x + b * g.HW * C;
  const int64_t row = g.K * C;
  for (int64_t t = 0; t < n; ++t) {
    const int64_t s0 = (item * g.P + p0 + t) * g.K;
    for (int64_t k = 0; k < g.K; ++k) {
      const int32_t* ix = index + (s0 + k) * 4;
      const Weights<T> w(frac + (s0 + k) * 2);
      const T* a[4];
      for (int c = 0; c < 4; ++c) {
        const int64_t rel = ix[c] - shift;
        a[c] = rel == g.HW ? zero : xb + rel * C;
      }
      T* dst = cols + t * row + k * Cg;
      if constexpr (NC > 0) {
        for (int i = 0; i < NC; ++i) {
          dst[i] = w[0] * a[0][i] + w[1] * a[1][i] + w[2] * a[2][i] + w[3] * a[3][i];
        }
      } else {
        for (int64_t gi = 0; gi < G; ++gi) {
          const int64_t o = gi * Cg;
          blend4(dst + gi * g.K * Cg, a[0] + o, a[1] + o, a[2] + o, a[3] + o, w[0], w[1], w[2],
                 w[3], Cg);
        }
      }
    }
  }
}

template <typename T>
void gather_columns(const Geo& g, const T* x, const int32_t* index, const T* frac, const T* zero,
                    int64_t b, int64_t p0, int64_t n, T* cols) {
  const auto run = [&](auto nc) {
    gather_columns_impl<T, decltype(nc)::value>(g, x, index, frac, zero, b, p0, n, cols);
  };
  switch (g.G == 1 ? g.C : 0) {
    case 1: return run(std::integral_constant<int, 1>());
    case 2: return run(std::integral_constant<int, 2>());
    case 3: return run(std::integral_constant<int, 3>());
    case 4: return run(std::integral_constant<int, 4>());
    default: return run(std::integral_constant<int, 0>());
  }
}

// Adds the column-gradient tile gcols [n, K*C] (layout as the columns) of output pixels
// [p0, p0 + n) of batch item b to the corners they sampled, in the channels-last buffer gx.
template <typename T>
void scatter_columns(const Geo& g, T* gx, const int32_t* index, const T* frac, int64_t b,
                     int64_t p0, int64_t n, const T* gcols) {
  const int64_t item = g.item(b);
  const int64_t shift = item * (g.HW + 1);
  T* gxb = gx + b * g.HW * g.C;
  const int64_t row = g.K * g.C;
  for (int64_t t = 0; t < n; ++t) {
    const int64_t s0 = (item * g.P + p0 + t) * g.K;
    for (int64_t k = 0; k < g.K; ++k) {
      const int32_t* ix = index + (s0 + k) * 4;
      const Weights<T> w(frac + (s0 + k) * 2);
      const T* src = gcols + t * row + k * g.Cg;
      for (int c = 0; c < 4; ++c) {
        const int64_t rel = ix[c] - shift;
        if (rel == g.HW || w[c] == T(0)) continue;
        T* dst = gxb + rel * g.C;
        for (int64_t gi = 0; gi < g.G; ++gi) {
          axpy(dst + gi * g.Cg, src + gi * g.K * g.Cg, w[c], g.Cg);
        }
      }
    }
  }
}

// Layout conversions between NCHW and channels-last, blocked for the caches (ATen's strided
// copy for a permutation is several times slower) and parallel over batch items and pixels.

// One item: [C, HW] -> [HW, C] (to_cl) or back, for pixels [p0, p0 + n), in tiles of CB
// channels x PB pixels. CB = 8 strided rows at a time: rows H*W apart alias in the L1 cache when
// H*W is a power of two, and 8 fit its associativity.
template <typename T>
void convert_pixels(const T* __restrict src, T* __restrict dst, int64_t C, int64_t HW,
                    int64_t p0, int64_t n, bool to_cl) {
  constexpr int64_t CB = 8, PB = 64;
  for (int64_t q0 = p0; q0 < p0 + n; q0 += PB) {
    const int64_t q1 = std::min(p0 + n, q0 + PB);
    for (int64_t c0 = 0; c0 < C; c0 += CB) {
      const int64_t c1 = std::min(C, c0 + CB);
      if (to_cl) {
        for (int64_t q = q0; q < q1; ++q)
          for (int64_t c = c0; c < c1; ++c) dst[q * C + c] = src[c * HW + q];
      } else {
        for (int64_t c = c0; c < c1; ++c)
          for (int64_t q = q0; q < q1; ++q) dst[c * HW + q] = src[q * C + c];
      }
    }
  }
}

// Copies x [B, C, H, W] (NCHW-contiguous if `to_cl`, else channels-last-contiguous) into dst of
// the other layout, in parallel over items and blocks of pixels.
template <typename T>
void convert_layout(const T* x, T* dst, int64_t B, int64_t C, int64_t HW, bool to_cl) {
  constexpr int64_t PIX = 1024;  // pixels per task
  const int64_t per_item = (HW + PIX - 1) / PIX;
  at::parallel_for(0, B * per_item, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / per_item, p0 = (t % per_item) * PIX;
      convert_pixels(x + b * C * HW, dst + b * C * HW, C, HW, p0, std::min(PIX, HW - p0), to_cl);
    }
  });
}

// The input as channels-last-contiguous (a view if it already is).
template <typename T>
at::Tensor channels_last(const at::Tensor& input) {
  if (input.is_contiguous(at::MemoryFormat::ChannelsLast)) return input;
  const at::Tensor x = input.contiguous();
  at::Tensor out = at::empty_like(x, x.options().memory_format(at::MemoryFormat::ChannelsLast));
  convert_layout<T>(x.const_data_ptr<T>(), out.mutable_data_ptr<T>(), x.size(0), x.size(1),
                    x.size(2) * x.size(3), true);
  return out;
}

// A channels-last-contiguous tensor as NCHW-contiguous.
template <typename T>
at::Tensor nchw(const at::Tensor& x) {
  at::Tensor out = at::empty_like(x, x.options().memory_format(at::MemoryFormat::Contiguous));
  convert_layout<T>(x.const_data_ptr<T>(), out.mutable_data_ptr<T>(), x.size(0), x.size(1),
                    x.size(2) * x.size(3), false);
  return out;
}

// The layout of the output (and input gradient) for an input: channels-last if the input is
// channels-last (as conv2d), else NCHW.
at::MemoryFormat memory_format(const at::Tensor& input) {
  return !input.is_contiguous() && input.is_contiguous(at::MemoryFormat::ChannelsLast)
             ? at::MemoryFormat::ChannelsLast
             : at::MemoryFormat::Contiguous;
}

// The weight packed as WP [G, C_out/G, K, C/G].
at::Tensor pack_weight(const at::Tensor& weight, const Geo& g) {
  return weight.reshape({g.G, g.Coutg, g.Cg, g.K}).transpose(2, 3).contiguous();
}

template <typename T>
at::Tensor forward_impl(const Geo& g, const at::Tensor& input, const at::Tensor& wp,
                        const at::Tensor& bias, const at::Tensor& index, const at::Tensor& frac) {
  const auto fmt = memory_format(input);
  const bool cl = fmt == at::MemoryFormat::ChannelsLast;
  const at::Tensor x = channels_last<T>(input);
  at::Tensor out = at::empty({g.B, g.Cout, g.Ho, g.Wo}, input.options().memory_format(fmt));
  const at::Tensor bias_c = bias.defined() ? bias.contiguous() : bias;
  const T* bp = bias.defined() ? bias_c.const_data_ptr<T>() : nullptr;
  const T* xp = x.const_data_ptr<T>();
  const T* wpp = wp.const_data_ptr<T>();
  const int32_t* ip = index.const_data_ptr<int32_t>();
  const T* fp = frac.const_data_ptr<T>();
  T* op = out.mutable_data_ptr<T>();
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  const int64_t tile = tile_rows(g.B, g.P, kc, g.Cout * kcg, sizeof(T));
  const int64_t tiles = (g.P + tile - 1) / tile;
  auto init = [&] { return Scratch<T>{std::vector<T>(tile * kc), std::vector<T>(g.C, T(0))}; };
  parallel_tasks(g.B * tiles, init, [&](int64_t task, Scratch<T>& s) {
    const int64_t b = task / tiles, p0 = (task % tiles) * tile;
    const int64_t n = std::min(tile, g.P - p0);
    gather_columns<T>(g, xp, ip, fp, s.zero.data(), b, p0, n, s.tile.data());
    for (int64_t gi = 0; gi < g.G; ++gi) {
      const Mat<const T> cols{s.tile.data() + gi * kcg, n, kcg, kc, 1};
      const Mat<const T> w{wpp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
      const Mat<T> c = out_block(g, op, cl, b, gi, p0, n);
      if (bp) {  // c = bias, then c += cols @ w^T
        const T* bg = bp + gi * g.Coutg;
        if (cl) {
          for (int64_t i = 0; i < n; ++i) std::copy(bg, bg + g.Coutg, c.p + i * c.rs);
        } else {
          for (int64_t j = 0; j < g.Coutg; ++j) std::fill(c.p + j * c.cs, c.p + j * c.cs + n, bg[j]);
        }
      }
      gemm<T>(cols, w.t(), c, bp != nullptr);
    }
  });
  return out;
}

// Gradient of the weight, [C_out, C/G, K] (the caller views the kernel dimensions).
template <typename T>
at::Tensor grad_weight_impl(const Geo& g, const at::Tensor& input, const at::Tensor& gy,
                            const at::Tensor& index, const at::Tensor& frac) {
  const bool cl = !gy.is_contiguous();  // else channels-last (see backward)
  const at::Tensor x = channels_last<T>(input);
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  const int64_t tile = tile_rows(g.B, g.P, kc, g.Cout * kcg, sizeof(T));
  const int64_t tiles = (g.P + tile - 1) / tile;
  const int64_t tasks = g.B * tiles;
  // One accumulator per chunk of tasks; chunks are fixed (not handed out dynamically) so that the
  // summation order, hence the result, is the same on every run with the same thread count.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), tasks));
  // Chunk 0 accumulates into the tensor that becomes the result, the others into a buffer freed
  // on return: the peak is `chunks` weights, not `chunks + 1`.
  at::Tensor gw = at::zeros({g.G, g.Coutg, g.K, g.Cg}, gy.options());
  at::Tensor rest = at::zeros({chunks - 1, g.G, g.Coutg, g.K, g.Cg}, gy.options());
  T* const gwp = gw.mutable_data_ptr<T>();
  T* const rp = rest.mutable_data_ptr<T>();
  const int64_t wsize = g.G * g.Coutg * kcg;
  const auto acc = [&](int64_t chunk) { return chunk == 0 ? gwp : rp + (chunk - 1) * wsize; };
  const T* xp = x.const_data_ptr<T>();
  const T* gp = gy.const_data_ptr<T>();
  const int32_t* ip = index.const_data_ptr<int32_t>();
  const T* fp = frac.const_data_ptr<T>();
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    std::vector<T> cols(tile * kc), zero(g.C, T(0));
    for (int64_t chunk = c0; chunk < c1; ++chunk) {
      T* accp = acc(chunk);
      for (int64_t task = chunk * tasks / chunks; task < (chunk + 1) * tasks / chunks; ++task) {
        const int64_t b = task / tiles, p0 = (task % tiles) * tile;
        const int64_t n = std::min(tile, g.P - p0);
        gather_columns<T>(g, xp, ip, fp, zero.data(), b, p0, n, cols.data());
        for (int64_t gi = 0; gi < g.G; ++gi) {
          const Mat<const T> c{cols.data() + gi * kcg, n, kcg, kc, 1};
          const Mat<const T> y = out_block(g, const_cast<T*>(gp), cl, b, gi, p0, n).as_const();
          const Mat<T> a{accp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
          gemm<T>(y.t(), c, a, true);
        }
      }
    }
  });
  // Sum the chunks into chunk 0 and swap (tap, channel) -> (channel, tap) in place, one output
  // channel (a row of K * C/G) at a time: [C_out, C/G, K].
  at::parallel_for(0, g.Cout, 1, [&](int64_t o0, int64_t o1) {
    std::vector<T> row(kcg);
    for (int64_t o = o0; o < o1; ++o) {
      T* r0 = gwp + o * kcg;
      for (int64_t i = 0; i < kcg; ++i) {
        T sum = r0[i];
        for (int64_t chunk = 1; chunk < chunks; ++chunk) sum += acc(chunk)[o * kcg + i];
        row[i] = sum;
      }
      for (int64_t k = 0; k < g.K; ++k) {
        for (int64_t c = 0; c < g.Cg; ++c) r0[c * g.K + k] = row[k * g.Cg + c];
      }
    }
  });
  return gw.view({g.Cout, g.Cg, g.K});
}

// Output pixels a scatter band should hold at least (its GEMMs repack the weight), unless that
// leaves fewer than MIN_BANDS bands per item (two per phase) to run in parallel.
constexpr int64_t BAND_PIXELS = 256;
constexpr int64_t MIN_BANDS = 4;

// Bands of output rows for the scatter: a band height R such that, within each of the two
// phases (even bands, odd bands), the input rows touched by different bands are disjoint, for
// every plan item. rows holds [items, H_out, 2] (lowest, highest input row read by an output
// row; lowest > highest when it reads none). R starts at the size preferred for the GEMMs and
// doubles until the bands are disjoint; it depends on the shapes and the plan only, never on the
// thread count, so neither does the summation order. Returns R (H_out: one band).
int64_t band_rows(const Geo& g, const int32_t* rows) {
  const int64_t items = g.per_item ? g.B : 1;
  const int64_t preferred = std::min((BAND_PIXELS + g.Wo - 1) / g.Wo, g.Ho / MIN_BANDS);
  for (int64_t r = std::max<int64_t>(1, preferred); r < g.Ho; r *= 2) {
    const int64_t bands = (g.Ho + r - 1) / r;
    bool ok = true;
    for (int64_t it = 0; it < items && ok; ++it) {
      const int32_t* ri = rows + it * g.Ho * 2;
      for (int64_t phase = 0; phase < 2 && ok; ++phase) {
        int64_t reach = INT64_MIN;  // highest input row of the earlier bands of this phase
        for (int64_t band = phase; band < bands && ok; band += 2) {
          int64_t lo = INT64_MAX, hi = INT64_MIN;
          for (int64_t oy = band * r; oy < std::min(g.Ho, (band + 1) * r); ++oy) {
            if (ri[2 * oy] > ri[2 * oy + 1]) continue;
            lo = std::min<int64_t>(lo, ri[2 * oy]);
            hi = std::max<int64_t>(hi, ri[2 * oy + 1]);
          }
          if (lo > hi) continue;
          ok = lo > reach;
          reach = std::max(reach, hi);
        }
      }
    }
    if (ok) return r;
  }
  return g.Ho;
}

// Input gradient, in the input's memory format.
template <typename T>
at::Tensor grad_input_impl(const Geo& g, const at::Tensor& input, const at::Tensor& wp,
                           const at::Tensor& gy, const at::Tensor& index, const at::Tensor& frac,
                           const at::Tensor& rows) {
  const bool cl_y = !gy.is_contiguous();  // else channels-last (see backward)
  // Channels-last accumulation buffer.
  at::Tensor gx =
      at::empty({g.B, g.C, g.H, g.W}, gy.options().memory_format(at::MemoryFormat::ChannelsLast))
          .zero_();
  const T* gp = gy.const_data_ptr<T>();
  const T* wpp = wp.const_data_ptr<T>();
  const int32_t* ip = index.const_data_ptr<int32_t>();
  const T* fp = frac.const_data_ptr<T>();
  T* xp = gx.mutable_data_ptr<T>();
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  const int64_t r = band_rows(g, rows.const_data_ptr<int32_t>());
  const int64_t bands = (g.Ho + r - 1) / r;
  const int64_t band_pixels = r * g.Wo;
  const int64_t tile = tile_rows(g.B, std::min(band_pixels, g.P), kc, g.Cout * kcg, sizeof(T));
  auto init = [&] { return Scratch<T>{std::vector<T>(tile * kc), {}}; };
  for (int64_t phase = 0; phase < 2; ++phase) {
    const int64_t phase_bands = (bands - phase + 1) / 2;
    parallel_tasks(g.B * phase_bands, init, [&](int64_t task, Scratch<T>& s) {
      const int64_t b = task / phase_bands, band = phase + 2 * (task % phase_bands);
      const int64_t end = std::min(g.P, (band + 1) * band_pixels);
      for (int64_t p0 = band * band_pixels; p0 < end; p0 += tile) {
        const int64_t n = std::min(tile, end - p0);
        for (int64_t gi = 0; gi < g.G; ++gi) {
          const Mat<const T> y = out_block(g, const_cast<T*>(gp), cl_y, b, gi, p0, n).as_const();
          const Mat<const T> w{wpp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
          const Mat<T> c{s.tile.data() + gi * kcg, n, kcg, kc, 1};
          gemm<T>(y, w, c, false);
        }
        scatter_columns<T>(g, xp, ip, fp, b, p0, n, s.tile.data());
      }
    });
  }
  if (memory_format(input) == at::MemoryFormat::ChannelsLast) return gx;
  return nchw<T>(gx);
}

struct DeformConv : public torch::autograd::Function<DeformConv> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& input,
                            const at::Tensor& weight, const at::Tensor& bias,
                            const at::Tensor& index, const at::Tensor& frac,
                            const at::Tensor& rows, int64_t ho, int64_t wo, int64_t groups,
                            bool per_item, bool has_bias) {
    const Geo g = geometry(input, weight.size(0), weight.size(2) * weight.size(3), ho, wo, groups,
                           per_item);
    const at::Tensor wp = pack_weight(weight, g);
    // The weight (a parameter, alive anyway) rather than its packed copy: the backward pass
    // repacks it, so no weight-sized buffer lives from forward to backward.
    ctx->save_for_backward({input, weight});
    ctx->saved_data["index"] = index;
    ctx->saved_data["frac"] = frac;
    ctx->saved_data["rows"] = rows;
    ctx->saved_data["ho"] = ho;
    ctx->saved_data["wo"] = wo;
    ctx->saved_data["groups"] = groups;
    ctx->saved_data["per_item"] = per_item;
    ctx->saved_data["has_bias"] = has_bias;
    at::Tensor out;
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_forward", [&] {
      out = forward_impl<scalar_t>(g, input, wp, has_bias ? bias : at::Tensor(), index, frac);
    });
    return out;
  }

  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    TORCH_CHECK(!at::GradMode::is_enabled(),
                "calibconv deform_conv2d: double backward (create_graph) is not supported");
    const auto saved = ctx->get_saved_variables();
    const at::Tensor& input = saved[0];
    const at::Tensor& weight = saved[1];
    auto& d = ctx->saved_data;
    const Geo g = geometry(input, weight.size(0), weight.size(2) * weight.size(3),
                           d["ho"].toInt(), d["wo"].toInt(), d["groups"].toInt(),
                           d["per_item"].toBool());
    // The output gradient is read in place if it is NCHW- or channels-last-contiguous.
    at::Tensor gy = grads[0];
    if (!gy.is_contiguous() && !gy.is_contiguous(at::MemoryFormat::ChannelsLast)) {
      gy = gy.contiguous(memory_format(input));
    }
    at::Tensor gx, gw, gb;
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_backward", [&] {
      if (ctx->needs_input_grad(1)) {
        gw = grad_weight_impl<scalar_t>(g, input, gy, d["index"].toTensor(), d["frac"].toTensor())
                 .view(weight.sizes());
      }
      if (ctx->needs_input_grad(0)) {
        gx = grad_input_impl<scalar_t>(g, input, pack_weight(weight, g), gy, d["index"].toTensor(),
                                       d["frac"].toTensor(), d["rows"].toTensor());
      }
    });
    if (d["has_bias"].toBool() && ctx->needs_input_grad(2)) {
      gb = gy.sum({0, 2, 3});
    }
    return {gx,           gw,           gb,           at::Tensor(), at::Tensor(), at::Tensor(),
            at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor()};
  }
};

char* error_string(const char* what) {
  const size_t n = std::strlen(what);
  char* s = static_cast<char*>(std::malloc(n + 1));
  if (s) std::memcpy(s, what, n + 1);
  return s;
}

}  // namespace

extern "C" {

// The deformable convolution of CPU tensors (contract in src/ops/native/mod.rs). On success
// writes a new tensor handle to *out and returns null; on failure returns a malloc'ed message
// (release it with calibconv_free_error).
char* calibconv_deform_conv2d_cpu(const at::Tensor* input, const at::Tensor* weight,
                                  const at::Tensor* bias, const at::Tensor* index,
                                  const at::Tensor* frac, const at::Tensor* rows, int64_t ho,
                                  int64_t wo, int64_t groups, int32_t per_item,
                                  at::Tensor** out) {
  try {
    // autograd Functions take defined tensors: no bias is an empty tensor and a flag.
    const at::Tensor none = bias ? at::Tensor() : at::empty({0}, input->options());
    at::Tensor y = DeformConv::apply(*input, *weight, bias ? *bias : none, *index, *frac, *rows, ho,
                                     wo, groups, per_item != 0, bias != nullptr);
    *out = new at::Tensor(std::move(y));
    return nullptr;
  } catch (const std::exception& e) {
    return error_string(e.what());
  } catch (...) {
    return error_string("unknown C++ exception");
  }
}

void calibconv_free_error(char* message) { std::free(message); }

}  // extern "C"
