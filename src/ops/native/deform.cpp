// Native CPU kernels of calibconv's deformable convolution with fixed offsets, as a
// torch::autograd::Function called from Rust (src/ops/native/mod.rs). The design and its
// numerics are documented in src/ops/mod.rs; in short, with K taps, C input and C_out output
// channels, G groups, and P output pixels:
//
// - The weight is packed per pass as WP [G, C_out/G, K, C/G] (the tap and channel axes of every
//   output channel swapped, a cheap local transpose); the backward pass repacks it rather than
//   keeping a weight-sized buffer alive between the passes.
// - forward: per tile of T output pixels (rows q = b * P + p of the whole batch), gather the
//   column tile [T, K*C] (layout: group, tap, channel) from the input padded channels-last
//   (pad_row; each thread pads the rows its tiles read, one item at a time, PaddedRows) with the
//   plan's top-left corners and the bilinear weights of its fractions (ly, lx), then
//   y[T, C_out] = cols @ WP^T + bias (one at::mm per group; oneDNN for float32 with one group
//   when asked, see use_dnn), copied into the output (NCHW or channels-last, as the input). A
//   first layer (input without gradient, <= 4 channels) keeps its whole column matrix for the
//   weight gradient, but for 3 float channels with the few-output-channel kernels
//   (three_channels): there the whole batch is gathered at once from a padded copy holding each
//   pixel's items side by side (with one plan for the batch), and the weight gradient gathers
//   the columns again.
// - backward, weight: the column tiles are recomputed (never stored; the rows padded again) and
//   acc_g[C_out/G, K*C/G] += gy_g^T @ cols_g, one accumulator per thread chunk, summed at the end.
// - backward, input: per tile, grad_cols_g = gy_g @ WP_g, then every sample adds w * grad_cols
//   to its four corners of the padded channels-last rows the task touches (a scatter, into a
//   per-thread buffer of one item's rows, GradientRows; the padding is dropped when the rows are
//   written out, or with Border::WrapX folded back into the first column). Tiles run in bands
//   of output rows, in two phases (even bands, then odd bands) chosen so that the input rows
//   that two bands of the same phase touch are disjoint: no atomics, no races, and the
//   summation order does not depend on the number of threads.
// - bias: a sum of the output gradient (with the few-output-channel kernels, summed block by
//   block in the weight gradient's pass, see grad_weight_impl).
// - few output channels (float32, one group, C_out 8 to 1024 with a weight of at most 36 MiB; 8
//   to 32 with AVX2): the three products run through register-blocked kernels on L1-sized blocks
//   of pixels (gathered, multiplied, scattered block by block) instead of a oneDNN / BLAS call
//   per tile, compiled per instruction-set level (AVX-512, AVX2) and picked at run time
//   (small_kernels.h, small.cpp).
//
// Tiles run in parallel with at::parallel_for. The entry point catches every C++ exception and
// returns its message: no exception crosses into Rust.
//
// Files: deform.h (shared declarations), gather.h / gather.cpp (the gather and scatter kernels),
// padding.cpp (the padded input), layout.cpp (NCHW <-> channels-last, the packed weight),
// forward.cpp, grad_weight.cpp, grad_input.cpp (the passes), small.cpp (the few-output-channel
// products in the layer), simd.h (instruction-set helpers), this file (tiling, the GEMM library,
// the autograd Function and the C entry points). What was measured for the choices in these files:
// docs/bench/cpu-kernels.md.

#include <ATen/ops/mkldnn_convolution.h>
#include <torch/csrc/autograd/custom_function.h>

#include <cstring>
#include <optional>
#include <string>

#include "gather.h"

namespace calibconv::native {

// Bytes of a gathered tile: the tile stays in the last-level cache and every GEMM is large
// enough to amortise packing the weight, which the BLAS does per call. A weight larger than
// TILE_BYTES per thread raises the budget to its share per thread (the GEMM then spends on the
// tile at least as much as on packing the weight).
constexpr int64_t TILE_BYTES = 2 << 20;
// Rows of a tile: enough that its GEMM does at least MIN_TILE_FLOP (a oneDNN call costs ~15 us,
// about 3 MFLOP of work: few channels need thousands of rows, 512 a few dozen), at least
// MIN_TILE, at most MAX_TILE.
constexpr int64_t MIN_TILE_FLOP = 8 << 20;
constexpr int64_t MIN_TILE = 64;
constexpr int64_t MAX_TILE = 8192;

int64_t tile_rows(int64_t total, int64_t row_elems, int64_t weight_elems, int64_t elem_bytes) {
  const int64_t threads = at::get_num_threads();
  const int64_t budget = std::max<int64_t>(TILE_BYTES, weight_elems * elem_bytes / threads);
  int64_t t = budget / std::max<int64_t>(1, row_elems * elem_bytes);
  t = std::max(t, MIN_TILE_FLOP / std::max<int64_t>(1, 2 * weight_elems));
  t = std::clamp<int64_t>(t - t % 16, MIN_TILE, MAX_TILE);
  t = std::min(t, (total + threads - 1) / threads);
  if (threads > 1 && t > 0) {  // (not below MIN_TILE unless t already is)
    const int64_t tiles = (total + t - 1) / t;
    const int64_t even = (tiles + threads - 1) / threads * threads;
    t = std::min(t, std::max(((total + even - 1) / even + 7) / 8 * 8, std::min(t, MIN_TILE)));
  }
  return std::max<int64_t>(t, 1);
}

bool whole_rows(int64_t total, int64_t row_elems, int64_t weight_elems) {
  return at::get_num_threads() > 1 && weight_elems >= total * row_elems;
}

// float32 GEMMs of one group (G = 1) that the few-output-channel kernels do not take go through the
// BLAS (at::mm, libtorch's MKL) by default, or through oneDNN as a 1x1 convolution
// (at::mkldnn_convolution) when asked (calibconv_native_gemm; `calibconv bench --gemm`, for A/B
// timings). These are the layers of more than 1024 outputs or a weight of more than 36 MiB (more
// than 32 outputs on CPUs without AVX-512), and the weight gradient from DNN_WEIGHT_MIN_COUT
// outputs where no few-output-channel kernel exists. At these shapes the BLAS measured faster than
// oneDNN (which also reorders the weight on every call, raising peak memory). Float64 (which
// oneDNN does not have) and grouped convolutions always use at::mm.
bool dnn_available() {
  static const bool ok = at::hasMKLDNN();
  return ok;
}

enum class Gemm : int32_t { Auto = 0, OneDnn = 1, Blas = 2 };
std::atomic<int32_t> gemm_override{static_cast<int32_t>(Gemm::Auto)};

// Whether the float32 GEMMs of one group go through oneDNN: only when asked for (see above).
bool use_dnn() {
  return dnn_available() && static_cast<Gemm>(gemm_override.load()) == Gemm::OneDnn;
}

at::Tensor dnn_linear(const Mat<const float>& a, const at::Tensor& w, const at::Tensor& bias) {
  auto opts = at::TensorOptions().dtype(at::kFloat);
  const at::Tensor img = at::from_blob(const_cast<float*>(a.p), {1, a.cols, 1, a.rows},
                                       {a.rows * a.cols, a.cs, a.rows * a.cols, a.rs}, opts);
  const at::Tensor w4 = w.contiguous().view({w.size(0), w.size(1), 1, 1});
  const std::optional<at::Tensor> b =
      bias.defined() ? std::optional<at::Tensor>(bias) : std::nullopt;
  const at::Tensor y = at::mkldnn_convolution(img, w4, b, {0, 0}, {1, 1}, {1, 1}, 1);
  return y.select(0, 0).select(1, 0).t();
}

Geo geometry(const at::Tensor& input, int64_t cout, int64_t k, int64_t ho, int64_t wo,
             int64_t groups, bool per_item, bool wrap) {
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
  g.Hp = g.H + 3;
  g.Wp = g.W + 2;
  g.wrap = wrap;
  return g;
}

std::atomic<bool> poison_scratch{false};


}  // namespace calibconv::native

namespace {

using namespace calibconv::native;
using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

struct DeformConv : public torch::autograd::Function<DeformConv> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& input,
                            const at::Tensor& weight, const at::Tensor& bias,
                            const at::Tensor& top_left,
                            const at::Tensor& frac, const at::Tensor& rows, int64_t ho,
                            int64_t wo, int64_t groups, bool per_item, bool wrap, bool has_bias,
                            bool grad_mode, int64_t out_layout) {
    const Geo g = geometry(input, weight.size(0), weight.size(2) * weight.size(3), ho, wo, groups,
                           per_item, wrap);
    // The weight (a parameter, alive anyway) rather than its packed copy: the backward pass
    // repacks it, so no weight-sized buffer lives from forward to backward.
    ctx->save_for_backward({input, weight});
    ctx->saved_data["top_left"] = top_left;
    // The per-sample coefficients the kernels read (sample_coefficients); the backward pass
    // computes them again from the fractions rather than keep the corner weights (16 bytes a
    // sample) from forward to backward.
    const at::Tensor coef = sample_coefficients(frac, g);
    ctx->saved_data["frac"] = frac;
    ctx->saved_data["rows"] = rows;
    ctx->saved_data["ho"] = ho;
    ctx->saved_data["wo"] = wo;
    ctx->saved_data["groups"] = groups;
    ctx->saved_data["per_item"] = per_item;
    ctx->saved_data["wrap"] = wrap;
    ctx->saved_data["has_bias"] = has_bias;
    // A first layer (its input, the image, needs no gradient) with few channels: its column
    // matrix is small (K*C values a pixel) and the weight gradient would gather it again, at a
    // cost close to the whole convolution's at 3 channels, so it is kept. Not without grad mode
    // (evaluation), where no backward pass follows; autograd runs this function with grad mode
    // off, so the caller's is an argument. (Float64 products go through the BLAS, whose last
    // bits can depend on the alignment of the rows: there a kept and a tiled column matrix may
    // differ by an ulp; float32's register-blocked products do not.)
    const bool first = grad_mode && !input.requires_grad() && weight.requires_grad();
    const bool is_float = input.scalar_type() == at::kFloat;
    const bool three = three_channels(g, is_float);
    const bool keep_cols = first && g.C <= KEEP_COLUMNS_MAX_C && g.G == 1 && !three;
    at::Tensor keep =
        keep_cols ? at::empty({g.B * g.P, g.K * g.C}, input.options()) : at::Tensor();
    ctx->saved_data["cols"] = keep_cols ? c10::IValue(keep) : c10::IValue();
    at::Tensor out;
    // The output in the input's layout, or the one asked for (out_layout: 1 channels-last,
    // 2 NCHW; the kernels write either from either input layout).
    const auto fmt = out_layout == 1   ? at::MemoryFormat::ChannelsLast
                     : out_layout == 2 ? at::MemoryFormat::Contiguous
                                       : memory_format(input);
    if (three && !g.per_item) {  // the whole batch at once (forward_batch)
      at::Tensor padded;
      out = forward_batch(g, input, weight, has_bias ? bias : at::Tensor(), top_left, coef, fmt,
                          &padded);
      ctx->saved_data["batch_input"] = first ? c10::IValue(padded) : c10::IValue();
      return out;
    }
    ctx->saved_data["batch_input"] = c10::IValue();
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_forward", [&] {
      out = forward_impl<scalar_t>(g, input, weight, has_bias ? bias : at::Tensor(), top_left,
                                   coef, rows, keep, fmt);
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
                           d["per_item"].toBool(), d["wrap"].toBool());
    // The output gradient is read in place if it is NCHW- or channels-last-contiguous.
    at::Tensor gy = grads[0];
    if (!gy.is_contiguous() && !gy.is_contiguous(at::MemoryFormat::ChannelsLast)) {
      gy = gy.contiguous(memory_format(input));
    }
    at::Tensor gx, gw, gb;
    const at::Tensor coef = sample_coefficients(d["frac"].toTensor(), g);
    AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_backward", [&] {
      const bool is_float = std::is_same_v<scalar_t, float>;
      if (ctx->needs_input_grad(1) && !ctx->needs_input_grad(0) && three_channels(g, is_float)) {
        // a first layer: its columns gathered again (grad_weight_first)
        const bool batched = d["batch_input"].isTensor();
        const at::Tensor x =
            batched ? d["batch_input"].toTensor() : padded_input<float>(input, g);
        gw = grad_weight_first(g, x, batched, gy, d["top_left"].toTensor(), coef)
                 .view(weight.sizes());
      } else if (ctx->needs_input_grad(1)) {
        const at::Tensor kept = d["cols"].isTensor() ? d["cols"].toTensor() : at::Tensor();
        auto [w, b] = grad_weight_impl<scalar_t>(
            g, input, gy, d["top_left"].toTensor(), coef, d["rows"].toTensor(),
            kept, d["has_bias"].toBool() && ctx->needs_input_grad(2));
        gw = w.view(weight.sizes());
        gb = b;  // (undefined where the weight gradient did not sum it)
      }
      if (ctx->needs_input_grad(0)) {
        gx = grad_input_impl<scalar_t>(g, input, pack_weight(weight, g), gy,
                                       d["top_left"].toTensor(), coef,
                                       d["rows"].toTensor());
      }
    });
    if (d["has_bias"].toBool() && ctx->needs_input_grad(2) && !gb.defined()) {
      gb = gy.sum({0, 2, 3});
    }
    return {gx,           gw,           gb,           at::Tensor(), at::Tensor(),
            at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor(),
            at::Tensor(), at::Tensor(), at::Tensor(), at::Tensor()};
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

using namespace calibconv::native;

// The deformable convolution of CPU tensors (contract in src/ops/native/mod.rs). On success
// writes a new tensor handle to *out and returns null; on failure returns a malloc'ed message
// (release it with calibconv_free_error).
char* calibconv_deform_conv2d_cpu(const at::Tensor* input, const at::Tensor* weight,
                                  const at::Tensor* bias, const at::Tensor* top_left,
                                  const at::Tensor* frac,
                                  const at::Tensor* rows, int64_t ho, int64_t wo, int64_t groups,
                                  int32_t per_item, int32_t wrap, int32_t out_layout,
                                  at::Tensor** out) {
  try {
    // autograd Functions take defined tensors: no bias is an empty tensor and a flag.
    const at::Tensor none = bias ? at::Tensor() : at::empty({0}, input->options());
    at::Tensor y = DeformConv::apply(*input, *weight, bias ? *bias : none, *top_left,
                                     *frac, *rows, ho, wo, groups, per_item != 0, wrap != 0,
                                     bias != nullptr, at::GradMode::is_enabled(),
                                     int64_t{out_layout});
    *out = new at::Tensor(std::move(y));
    return nullptr;
  } catch (const std::exception& e) {
    return error_string(e.what());
  } catch (...) {
    return error_string("unknown C++ exception");
  }
}

void calibconv_free_error(char* message) { std::free(message); }

// The library of the float32 GEMMs that the few-output-channel kernels do not take: sets it when
// choice >= 0 (0 the default (the BLAS), 1 oneDNN, 2 the BLAS; oneDNN only where libtorch has it),
// then returns the library in use (1 oneDNN, 2 the BLAS).
int32_t calibconv_native_gemm(int32_t choice) {
  if (choice >= 0 && choice <= 2) gemm_override.store(choice);
  return use_dnn() ? 1 : 2;
}

// The instruction-set level of the few-output-channel kernels: caps it at `cap` (0 none, 1 AVX2,
// 2 AVX-512) when cap >= 0, then returns the level in use (the CPU's, at most the cap).
int32_t calibconv_native_small_isa(int32_t cap) {
  if (cap >= 0) small_isa_cap.store(std::min<int32_t>(cap, static_cast<int32_t>(SmallIsa::Avx512)));
  return static_cast<int32_t>(small_isa());
}

// The library of the large weights' products (see large_weights_to_blas): sets it when choice
// >= 0 (0 the CPU's default, 1 the few-output-channel kernels, 2 the BLAS), then returns the one in
// use (1 the kernels, 2 the BLAS).
int32_t calibconv_native_large_weights(int32_t choice) {
  if (choice >= 0 && choice <= 2) large_weights_override.store(choice);
  return large_weights_to_blas() ? 2 : 1;
}

// Poisons the scratch buffers that are written before they are read (see Uninit) from now on
// when on > 0, stops when on == 0; returns whether they are poisoned.
int32_t calibconv_native_poison_scratch(int32_t on) {
  if (on >= 0) poison_scratch.store(on > 0);
  return poison_scratch.load() ? 1 : 0;
}

}  // extern "C"
