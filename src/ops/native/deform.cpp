// Native CPU kernels of calibconv's deformable convolution with fixed offsets, as a
// torch::autograd::Function. The design and its numerics are documented in src/ops/mod.rs; in
// short:
//
// - forward: per tile of output pixels, gather the column tile [T, K*C] (layout: group, tap,
//   channel) from a channels-last copy of the input with the plan's four bilinear corners and
//   weights, then one GEMM per group with the packed weight [K*Cg, Cout/G] writes the output
//   tile in place (NCHW or channels-last, as the input).
// - backward, weight: the column tiles are recomputed (never stored) and multiplied with the
//   output gradient into one accumulator per thread, summed at the end.
// - backward, input: a gather through the transposed plan (for every input pixel and tap, the
//   output pixels that sample it and their bilinear weights, CSR) builds the tile [T, K*Cout]
//   of weighted output gradients, and one GEMM per group with the weight gives the input
//   gradient tile. No scatter, no atomics, no column-sized buffer.
// - bias: a sum of the output gradient.
//
// Tiles run in parallel with at::parallel_for. Every entry point catches C++ exceptions and
// returns their message: no exception crosses into Rust.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/csrc/autograd/custom_function.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// Bytes of a gathered tile ([T, K*C] columns or [T, K*C_out] gradients): large enough that the
// per-tile GEMM amortises streaming the weight, small enough to stay in L2/L3.
constexpr int64_t TILE_BYTES = 1 << 20;
constexpr int64_t MIN_TILE = 64;
constexpr int64_t MAX_TILE = 1024;

int64_t tile_rows(int64_t row_elems, int64_t elem_bytes) {
  int64_t t = TILE_BYTES / std::max<int64_t>(1, row_elems * elem_bytes);
  t = std::clamp<int64_t>(t, MIN_TILE, MAX_TILE);
  return t - t % 16 > 0 ? t - t % 16 : t;
}

// ---------------------------------------------------------------------------------------------
// Inner loops. Written once per element type (not as templates) so that they can be compiled
// for several instruction sets and picked at load time (GCC/Clang function multiversioning).

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__)) && !defined(__INTEL_COMPILER)
#define CALIBCONV_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define CALIBCONV_CLONES
#endif

// dst[i] = w0 a0[i] + w1 a1[i] + w2 a2[i] + w3 a3[i]
#define CALIBCONV_BLEND4(T, NAME)                                                             \
  CALIBCONV_CLONES void NAME(T* __restrict dst, const T* __restrict a0, const T* __restrict a1, \
                             const T* __restrict a2, const T* __restrict a3, T w0, T w1, T w2,   \
                             T w3, int64_t n) {                                                  \
    for (int64_t i = 0; i < n; ++i) {                                                            \
      dst[i] = w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i];                                \
    }                                                                                            \
  }
CALIBCONV_BLEND4(float, blend4_f32)
CALIBCONV_BLEND4(double, blend4_f64)

// dst[i] += w0 a0[i] + w1 a1[i] + w2 a2[i] + w3 a3[i]
#define CALIBCONV_ACC4(T, NAME)                                                               \
  CALIBCONV_CLONES void NAME(T* __restrict dst, const T* __restrict a0, const T* __restrict a1, \
                             const T* __restrict a2, const T* __restrict a3, T w0, T w1, T w2,   \
                             T w3, int64_t n) {                                                  \
    for (int64_t i = 0; i < n; ++i) {                                                            \
      dst[i] += w0 * a0[i] + w1 * a1[i] + w2 * a2[i] + w3 * a3[i];                               \
    }                                                                                            \
  }
CALIBCONV_ACC4(float, acc4_f32)
CALIBCONV_ACC4(double, acc4_f64)

inline void blend4(float* d, const float* a0, const float* a1, const float* a2, const float* a3,
                   float w0, float w1, float w2, float w3, int64_t n) {
  blend4_f32(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
}
inline void blend4(double* d, const double* a0, const double* a1, const double* a2,
                   const double* a3, double w0, double w1, double w2, double w3, int64_t n) {
  blend4_f64(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
}
inline void acc4(float* d, const float* a0, const float* a1, const float* a2, const float* a3,
                 float w0, float w1, float w2, float w3, int64_t n) {
  acc4_f32(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
}
inline void acc4(double* d, const double* a0, const double* a1, const double* a2,
                 const double* a3, double w0, double w1, double w2, double w3, int64_t n) {
  acc4_f64(d, a0, a1, a2, a3, w0, w1, w2, w3, n);
}

// ---------------------------------------------------------------------------------------------
// GEMM on raw, strided matrices through ATen (which calls the BLAS libtorch was built with).

// A row-major-or-column-major matrix: element (i, j) at p[i * rs + j * cs].
template <typename T>
struct Mat {
  T* p;
  int64_t rows, cols, rs, cs;
};

template <typename T>
at::Tensor view_of(const Mat<T>& m) {
  auto opts = at::TensorOptions().dtype(c10::CppTypeToScalarType<std::remove_const_t<T>>::value);
  return at::from_blob(const_cast<std::remove_const_t<T>*>(m.p), {m.rows, m.cols}, {m.rs, m.cs},
                       opts);
}

// c = a @ b (beta == 0: c is not read) or c += a @ b (beta == 1).
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
// Geometry of one call.

struct Geo {
  int64_t B, C, H, W, HW, Ho, Wo, P, K, G, Cg, Cout, Coutg;
  bool per_item;  // the plan holds one set of samples per batch item
  // Plan item of batch item b.
  int64_t item(int64_t b) const { return per_item ? b : 0; }
};

// Runs f(task, scratch) for task in [0, n) on the intra-op threads, handing tasks out
// dynamically (the machine may be shared: a slow thread does fewer tiles); every thread makes its
// scratch with init() once. Results must not depend on which thread runs a task.
template <typename Init, typename F>
void parallel_tasks(int64_t n, const Init& init, const F& f) {
  std::atomic<int64_t> next{0};
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), n));
  at::parallel_for(0, threads, 1, [&](int64_t, int64_t) {
    auto scratch = init();
    for (int64_t t = next++; t < n; t = next++) {
      f(t, scratch);
    }
  });
}

// Per-thread buffers: a gathered tile and a zero vector for out-of-range corners.
template <typename T>
struct Scratch {
  std::vector<T> tile, zero;
};

// Gathers the column tile of output pixels [p0, p0 + n) of batch item b into cols [n, K*C]
// (layout: group, tap, channel within the group).
template <typename T>
void gather_columns(const Geo& g, const T* x, const int32_t* index, const T* pw, const T* zero,
                    int64_t b, int64_t p0, int64_t n, T* cols) {
  const int64_t item = g.item(b);
  const int64_t shift = item * (g.HW + 1);  // per-item plans index a stacked table
  const T* xb = x + b * g.HW * g.C;
  const int64_t row = g.K * g.C;
  for (int64_t t = 0; t < n; ++t) {
    const int64_t s0 = ((item * g.P) + p0 + t) * g.K;
    for (int64_t k = 0; k < g.K; ++k) {
      const int32_t* ix = index + (s0 + k) * 4;
      const T* w = pw + (s0 + k) * 4;
      const T* a[4];
      for (int c = 0; c < 4; ++c) {
        const int64_t rel = ix[c] - shift;
        a[c] = rel == g.HW ? zero : xb + rel * g.C;
      }
      T* dst = cols + t * row + k * g.Cg;
      for (int64_t gi = 0; gi < g.G; ++gi) {
        const int64_t o = gi * g.Cg;
        blend4(dst + gi * g.K * g.Cg, a[0] + o, a[1] + o, a[2] + o, a[3] + o, w[0], w[1], w[2],
               w[3], g.Cg);
      }
    }
  }
}

// Gathers the weighted output gradients of input pixels [q0, q0 + n) of batch item b through the
// transposed plan into gt [n, K*C_out] (layout: group, tap, output channel within the group).
template <typename T>
void gather_grad(const Geo& g, const T* gy, const int32_t* tptr, const int32_t* tsrc,
                 const T* twt, const T* zero, int64_t b, int64_t q0, int64_t n, T* gt) {
  const int64_t item = g.item(b);
  const T* gyb = gy + b * g.P * g.Cout;
  const int64_t row = g.K * g.Cout;
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = 0; k < g.K; ++k) {
      const int64_t r = (item * g.K + k) * g.HW + q0 + t;
      int64_t e = tptr[r];
      const int64_t end = tptr[r + 1];
      T* dst = gt + t * row + k * g.Coutg;
      bool first = true;
      do {
        const T* a[4];
        T w[4];
        for (int c = 0; c < 4; ++c, ++e) {
          if (e < end) {
            a[c] = gyb + int64_t(tsrc[e]) * g.Cout;
            w[c] = twt[e];
          } else {
            a[c] = zero;
            w[c] = T(0);
          }
        }
        for (int64_t gi = 0; gi < g.G; ++gi) {
          const int64_t o = gi * g.Coutg;
          T* d = dst + gi * g.K * g.Coutg;
          if (first) {
            blend4(d, a[0] + o, a[1] + o, a[2] + o, a[3] + o, w[0], w[1], w[2], w[3], g.Coutg);
          } else {
            acc4(d, a[0] + o, a[1] + o, a[2] + o, a[3] + o, w[0], w[1], w[2], w[3], g.Coutg);
          }
        }
        first = false;
      } while (e < end);
    }
  }
}

template <typename T>
at::Tensor forward_impl(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                        const at::Tensor& bias, const at::Tensor& index, const at::Tensor& pw) {
  const auto fmt = input.suggest_memory_format();
  const at::Tensor x = input.contiguous(at::MemoryFormat::ChannelsLast);
  // Packed weight [G, K, Cg, Cout/G]: row (tap, channel) of the columns times output channel.
  const at::Tensor w1 = weight.reshape({g.G, g.Coutg, g.Cg, g.K}).permute({0, 3, 2, 1}).contiguous();
  at::Tensor out = at::empty({g.B, g.Cout, g.Ho, g.Wo}, input.options().memory_format(fmt));
  const bool cl = fmt == at::MemoryFormat::ChannelsLast;
  const T* xp = x.const_data_ptr<T>();
  const T* wp = w1.const_data_ptr<T>();
  const at::Tensor bias_c = bias.defined() ? bias.contiguous() : bias;
  const T* bp = bias.defined() ? bias_c.const_data_ptr<T>() : nullptr;
  const int32_t* ip = index.const_data_ptr<int32_t>();
  const T* pwp = pw.const_data_ptr<T>();
  T* op = out.mutable_data_ptr<T>();
  const int64_t tile = tile_rows(g.K * g.C, sizeof(T));
  const int64_t tiles = (g.P + tile - 1) / tile;
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  auto init = [&] { return Scratch<T>{std::vector<T>(tile * kc), std::vector<T>(g.C, T(0))}; };
  parallel_tasks(g.B * tiles, init, [&](int64_t task, Scratch<T>& s) {
    const int64_t b = task / tiles, p0 = (task % tiles) * tile;
    const int64_t n = std::min(tile, g.P - p0);
    gather_columns<T>(g, xp, ip, pwp, s.zero.data(), b, p0, n, s.tile.data());
    for (int64_t gi = 0; gi < g.G; ++gi) {
      Mat<const T> a{s.tile.data() + gi * kcg, n, kcg, kc, 1};
      Mat<const T> w{wp + gi * kcg * g.Coutg, kcg, g.Coutg, g.Coutg, 1};
      Mat<T> c = cl ? Mat<T>{op + (b * g.P + p0) * g.Cout + gi * g.Coutg, n, g.Coutg, g.Cout, 1}
                    : Mat<T>{op + (b * g.Cout + gi * g.Coutg) * g.P + p0, n, g.Coutg, 1, g.P};
      if (bp) {  // c = bias, then c += a @ w
        const T* bg = bp + gi * g.Coutg;
        if (cl) {
          for (int64_t i = 0; i < n; ++i) std::copy(bg, bg + g.Coutg, c.p + i * c.rs);
        } else {
          for (int64_t j = 0; j < g.Coutg; ++j) std::fill(c.p + j * c.cs, c.p + j * c.cs + n, bg[j]);
        }
      }
      gemm<T>(a, w, c, bp != nullptr);
    }
  });
  return out;
}

template <typename T>
at::Tensor grad_weight_impl(const Geo& g, const at::Tensor& input, const at::Tensor& gy,
                            const at::Tensor& index, const at::Tensor& pw) {
  const at::Tensor x = input.contiguous(at::MemoryFormat::ChannelsLast);
  const int64_t tile = tile_rows(g.K * g.C, sizeof(T));
  const int64_t tiles = (g.P + tile - 1) / tile;
  const int64_t tasks = g.B * tiles;
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  // One accumulator [G, K, Cg, Cout/G] per chunk of tasks; chunks are fixed (not dynamic) so
  // that the summation order, hence the result, is the same on every run.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), tasks));
  at::Tensor acc = at::zeros({chunks, g.G, g.K, g.Cg, g.Coutg}, gy.options());
  const T* xp = x.const_data_ptr<T>();
  const T* gp = gy.const_data_ptr<T>();
  const int32_t* ip = index.const_data_ptr<int32_t>();
  const T* pwp = pw.const_data_ptr<T>();
  T* ap = acc.mutable_data_ptr<T>();
  const int64_t wsize = g.G * kcg * g.Coutg;
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    std::vector<T> cols(tile * kc), zero(g.C, T(0));
    for (int64_t chunk = c0; chunk < c1; ++chunk) {
      T* accp = ap + chunk * wsize;
      for (int64_t task = chunk * tasks / chunks; task < (chunk + 1) * tasks / chunks; ++task) {
        const int64_t b = task / tiles, p0 = (task % tiles) * tile;
        const int64_t n = std::min(tile, g.P - p0);
        gather_columns<T>(g, xp, ip, pwp, zero.data(), b, p0, n, cols.data());
        for (int64_t gi = 0; gi < g.G; ++gi) {
          Mat<const T> a{cols.data() + gi * kcg, kcg, n, 1, kc};  // columns, transposed
          Mat<const T> y{gp + (b * g.P + p0) * g.Cout + gi * g.Coutg, n, g.Coutg, g.Cout, 1};
          Mat<T> c{accp + gi * kcg * g.Coutg, kcg, g.Coutg, g.Coutg, 1};
          gemm<T>(a, y, c, true);
        }
      }
    }
  });
  // [G, K, Cg, Cout/G] -> [C_out, Cg, kh, kw] (the caller views the kernel dimensions).
  return acc.sum(0).permute({0, 3, 2, 1}).reshape({g.Cout, g.Cg, g.K});
}

template <typename T>
at::Tensor grad_input_impl(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                           const at::Tensor& gy, const at::Tensor& tptr, const at::Tensor& tsrc,
                           const at::Tensor& twt) {
  const auto fmt = input.suggest_memory_format();
  const bool cl = fmt == at::MemoryFormat::ChannelsLast;
  // Packed weight [G, K, Cout/G, Cg]: row (tap, output channel) times input channel.
  const at::Tensor w2 = weight.reshape({g.G, g.Coutg, g.Cg, g.K}).permute({0, 3, 1, 2}).contiguous();
  at::Tensor gx = at::empty({g.B, g.C, g.H, g.W}, gy.options().memory_format(fmt));
  const T* gp = gy.const_data_ptr<T>();
  const T* wp = w2.const_data_ptr<T>();
  const int32_t* rp = tptr.const_data_ptr<int32_t>();
  const int32_t* sp = tsrc.const_data_ptr<int32_t>();
  const T* tw = twt.const_data_ptr<T>();
  T* xp = gx.mutable_data_ptr<T>();
  const int64_t tile = tile_rows(g.K * g.Cout, sizeof(T));
  const int64_t tiles = (g.HW + tile - 1) / tile;
  const int64_t ko = g.K * g.Cout, kog = g.K * g.Coutg;
  auto init = [&] { return Scratch<T>{std::vector<T>(tile * ko), std::vector<T>(g.Cout, T(0))}; };
  parallel_tasks(g.B * tiles, init, [&](int64_t task, Scratch<T>& s) {
    const int64_t b = task / tiles, q0 = (task % tiles) * tile;
    const int64_t n = std::min(tile, g.HW - q0);
    gather_grad<T>(g, gp, rp, sp, tw, s.zero.data(), b, q0, n, s.tile.data());
    for (int64_t gi = 0; gi < g.G; ++gi) {
      Mat<const T> a{s.tile.data() + gi * kog, n, kog, ko, 1};
      Mat<const T> w{wp + gi * kog * g.Cg, kog, g.Cg, g.Cg, 1};
      Mat<T> c = cl ? Mat<T>{xp + (b * g.HW + q0) * g.C + gi * g.Cg, n, g.Cg, g.C, 1}
                    : Mat<T>{xp + (b * g.C + gi * g.Cg) * g.HW + q0, n, g.Cg, 1, g.HW};
      gemm<T>(a, w, c, false);
    }
  });
  return gx;
}

Geo geometry(const at::Tensor& input, const at::Tensor& weight, int64_t ho, int64_t wo,
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
  g.K = weight.size(2) * weight.size(3);
  g.G = groups;
  g.Cg = g.C / groups;
  g.Cout = weight.size(0);
  g.Coutg = g.Cout / groups;
  g.per_item = per_item;
  return g;
}

struct DeformConv : public torch::autograd::Function<DeformConv> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& input,
                            const at::Tensor& weight, const at::Tensor& bias,
                            const at::Tensor& index, const at::Tensor& pw,
                            const at::Tensor& tptr, const at::Tensor& tsrc,
                            const at::Tensor& twt, int64_t ho, int64_t wo, int64_t groups,
                            bool per_item, bool has_bias) {
    const Geo g = geometry(input, weight, ho, wo, groups, per_item);
    ctx->save_for_backward({input, weight});
    ctx->saved_data["index"] = index;
    ctx->saved_data["pw"] = pw;
    ctx->saved_data["tptr"] = tptr;
    ctx->saved_data["tsrc"] = tsrc;
    ctx->saved_data["twt"] = twt;
    ctx->saved_data["ho"] = ho;
    ctx->saved_data["wo"] = wo;
    ctx->saved_data["groups"] = groups;
    ctx->saved_data["per_item"] = per_item;
    ctx->saved_data["has_bias"] = has_bias;
    at::Tensor out;
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_forward", [&] {
      out = forward_impl<scalar_t>(g, input, weight, has_bias ? bias : at::Tensor(), index, pw);
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
    const Geo g = geometry(input, weight, d["ho"].toInt(), d["wo"].toInt(),
                           d["groups"].toInt(), d["per_item"].toBool());
    // Output gradient, channels-last: [B, P, C_out] rows for the gathers and GEMMs.
    const at::Tensor gy = grads[0].contiguous(at::MemoryFormat::ChannelsLast);
    at::Tensor gx, gw, gb;
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_backward", [&] {
      if (ctx->needs_input_grad(1)) {
        gw = grad_weight_impl<scalar_t>(g, input, gy, d["index"].toTensor(), d["pw"].toTensor())
                 .view(weight.sizes());
      }
      if (ctx->needs_input_grad(0)) {
        gx = grad_input_impl<scalar_t>(g, input, weight, gy, d["tptr"].toTensor(),
                                       d["tsrc"].toTensor(), d["twt"].toTensor());
      }
    });
    if (d["has_bias"].toBool() && ctx->needs_input_grad(2)) {
      gb = grads[0].sum({0, 2, 3});
    }
    return {gx, gw, gb, at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor(),
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

// The deformable convolution on CPU tensors (see src/ops/native.rs for the contract). On success
// writes a new tensor handle to *out and returns null; on failure returns a malloc'ed message.
char* calibconv_deform_conv2d_cpu(const at::Tensor* input, const at::Tensor* weight,
                                  const at::Tensor* bias, const at::Tensor* index,
                                  const at::Tensor* pw, const at::Tensor* tptr,
                                  const at::Tensor* tsrc, const at::Tensor* twt, int64_t ho,
                                  int64_t wo, int64_t groups, int32_t per_item, at::Tensor** out) {
  try {
    // autograd Functions take defined tensors only: no bias is an empty one and a flag.
    const at::Tensor none = bias ? at::Tensor() : at::empty({0}, input->options());
    at::Tensor y = DeformConv::apply(*input, *weight, bias ? *bias : none, *index, *pw, *tptr,
                                     *tsrc, *twt, ho, wo, groups, per_item != 0, bias != nullptr);
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
