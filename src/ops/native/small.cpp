// The few-output-channel products (small_kernels.h) in the deformable convolution: which passes
// take them, the weight in panels, and the first layers of 3 channels that gather the whole batch
// at once (forward_batch, grad_weight_first). What was measured for the choices below:
// docs/bench/cpu-kernels.md.

#include "gather.h"

#include <algorithm>
#include <type_traits>

namespace calibconv::native {

// Which library multiplies large weights (more than BLAS_WEIGHT values, 4 MiB: from
// 256->512 and 512->256 on) where the few-output-channel kernels exist: 0 the CPU's default, 1
// the kernels, 2 the BLAS (calibconv_native_large_weights; `calibconv bench --large-weights`).
// The default is the BLAS where it is MKL on an Intel CPU, the kernels elsewhere. MKL runs its
// AVX-512 code on Intel CPUs only (on AMD ones its AVX2 code, which the kernels beat at every
// shape measured, see small_kernels.h). On an Intel Xeon with AVX-512 (and AMX) MKL's column and
// weight gradients beat the kernels' for weights over BLAS_WEIGHT values, and its forward beats
// theirs there on passes of fewer than BLAS_FORWARD_MIN_ROWS rows; below BLAS_WEIGHT the kernels
// win all three products.
std::atomic<int32_t> large_weights_override{static_cast<int32_t>(LargeWeights::Auto)};
// Weights over BLAS_WEIGHT values go to the BLAS: their gradients always, their forward on
// fewer than BLAS_FORWARD_MIN_ROWS rows a pass.
constexpr int64_t BLAS_WEIGHT = 1 << 20;
constexpr int64_t BLAS_FORWARD_MIN_ROWS = 1024;

bool large_weights_to_blas() {
  switch (static_cast<LargeWeights>(large_weights_override.load())) {
    case LargeWeights::Kernels:
      return false;
    case LargeWeights::Blas:
      return true;
    default:
      break;
  }
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
  static const bool intel_mkl = [] {
    __builtin_cpu_init();
    return at::hasMKL() && __builtin_cpu_is("intel");
  }();
  return intel_mkl;
#else
  return false;
#endif
}

// The few-output-channel kernels (small_kernels.h) of a pass, or all null. A pass of whole_rows
// (a weight larger than the column matrix, with more than one thread) keeps them when every
// thread still gets SMALL_LARGE_BLOCK_ROWS rows or more: each thread's tile then reads the whole
// weight once per such block, as one thread does, and the weight gradient splits the panels
// between the threads (grad_weight_impl). With fewer rows a thread such a pass goes through the
// BLAS's multithreaded products (one tile per thread would give each a weight-sized gradient
// accumulator; see whole_rows).
template <typename T>
SmallKernels small_kernels(const Geo& g) {
  if (!std::is_same_v<T, float> || g.G != 1) return {};
  const int64_t total = g.B * g.P, kc = g.K * g.C;
  if (whole_rows(total, kc, g.Cout * kc) &&
      total < at::get_num_threads() * SMALL_LARGE_BLOCK_ROWS) {
    return {};
  }
  SmallKernels s = small_kernels_for(g.Cout, kc);
  const int64_t weight = kc * g.Cout;
  if (s && weight > BLAS_WEIGHT && large_weights_to_blas()) {
    if (total < BLAS_FORWARD_MIN_ROWS) return {};
    s.column_gradient = nullptr;
    s.weight_gradient = nullptr;
  }
  return s;
}
template SmallKernels small_kernels<float>(const Geo&);
template SmallKernels small_kernels<double>(const Geo&);

// Between a float32 weight [C_out, C, K] of one group and its panels [C_out / P, K*C, P] (P =
// small_panel(C_out); rows in the columns' (tap, channel) order, see weight_columns), either way:
// 8x8 register transposes of 8 outputs by 8 consecutive (channel, tap) values of their rows, each
// of the 8 values' panel rows its own pointer. Per panel the blocks go along the weight's rows
// with the panel's P / 8 output groups innermost, so that a panel row is written (or read) whole,
// P contiguous values, at once. C_out is a multiple of 8.
template <bool TO_PANELS>
CALIBCONV_ALWAYS_INLINE inline void weight_panels_body(const float* __restrict src,
                                                       float* __restrict dst, int64_t Cout,
                                                       int64_t C, int64_t K) {
  const int64_t P = small_panel(Cout), kc = K * C;
  for (int64_t p0 = 0; p0 < Cout; p0 += P) {
    const int64_t base = p0 * kc;  // the panel's offset, and its first output's row
    int64_t c = 0, k = 0;          // (channel, tap) of the weight's value j
    int64_t j = 0;
    for (; j + 8 <= kc; j += 8) {
      int64_t row[8];  // the panel rows of values j .. j + 7
      for (int i = 0; i < 8; ++i) {
        row[i] = base + (k * C + c) * P;
        if (++k == K) k = 0, ++c;
      }
      for (int64_t o = 0; o < P; o += 8) {
        // the 8 outputs' rows in the weight (from output p0 + o, value j) and in the panel
        int64_t wr[8], pr[8];
        for (int i = 0; i < 8; ++i) wr[i] = base + (o + i) * kc + j, pr[i] = row[i] + o;
        const int64_t(&from)[8] = TO_PANELS ? wr : pr;
        const int64_t(&to)[8] = TO_PANELS ? pr : wr;
        const float* const s[8] = {src + from[0], src + from[1], src + from[2], src + from[3],
                                   src + from[4], src + from[5], src + from[6], src + from[7]};
        float* const d[8] = {dst + to[0], dst + to[1], dst + to[2], dst + to[3],
                             dst + to[4], dst + to[5], dst + to[6], dst + to[7]};
        transpose8x8_rows(s, d);
      }
    }
    for (; j < kc; ++j) {  // the last kc % 8 values, one at a time
      const int64_t r = base + (k * C + c) * P;
      for (int64_t o = 0; o < P; ++o) {
        const int64_t w = base + o * kc + j;
        dst[TO_PANELS ? r + o : w] = src[TO_PANELS ? w : r + o];
      }
      if (++k == K) k = 0, ++c;
    }
  }
}
CALIBCONV_CLONES void weight_to_panels(const float* __restrict w, float* __restrict panels,
                                       int64_t Cout, int64_t C, int64_t K) {
  weight_panels_body<true>(w, panels, Cout, C, K);
}
CALIBCONV_CLONES void panels_to_weight(const float* __restrict panels, float* __restrict w,
                                       int64_t Cout, int64_t C, int64_t K) {
  weight_panels_body<false>(panels, w, Cout, C, K);
}

at::Tensor weight_columns(const at::Tensor& weight, const Geo& g) {
  const at::Tensor wc = weight.contiguous();
  const int64_t P = small_panel(g.Cout), kc = g.K * g.C;
  at::Tensor wt = at::empty({g.Cout / P, kc, P}, weight.options());
  const float* w = wc.const_data_ptr<float>();
  float* d = wt.mutable_data_ptr<float>();
  // Panels in parallel (the pass runs before the tiles' parallel loop).
  at::parallel_for(0, g.Cout / P, 1, [&](int64_t p0, int64_t p1) {
    weight_to_panels(w + p0 * P * kc, d + p0 * P * kc, (p1 - p0) * P, g.C, g.K);
  });
  return wt;
}

// An item's block is a multiple of the forward kernel's rows at a time (small.rows): the kernels
// are called once per item and block, and a row left over is multiplied alone, one dependent
// multiply-add after the other. The weight gradient (grad_weight_first) adds its rows block by
// block, item by item, so the block size sets the order of its sums.
BatchTiles batch_tiles(const Geo& g, const SmallKernels& small) {
  const int64_t kc = g.K * g.C;
  const int64_t tile = tile_rows(g.B * g.P, kc, g.Cout * kc, sizeof(float));
  const int64_t per_task = std::max<int64_t>(1, tile / g.B);
  const int64_t r = std::max<int64_t>(1, small.rows);
  const int64_t per_item = std::max<int64_t>(1, small_block_rows(kc, g.Cout, tile) / g.B);
  return {per_task, (per_item + r - 1) / r * r, (g.P + per_task - 1) / per_task};
}

// 3 float channels (an RGB image: a first layer) in one group, with the few-output-channel kernels
// and at least four items (fewer leave the vectors of four items partly empty). With one plan for
// every item the forward pass gathers the whole batch at once (padded_batch_input, batch_gather);
// as a first layer (the input needs no gradient) its weight gradient goes through pixel blocks of
// all items (grad_weight_first), the columns gathered again rather than kept (writing the kept
// column matrix, 9 values a pixel for every value of the input, to memory bound the gather; the
// batch path is faster and needs less memory).
bool three_channels(const Geo& g, bool is_float) {
  return is_float && g.C == 3 && g.G == 1 && g.B >= 4 && small_kernels<float>(g);
}

at::Tensor grad_weight_first(const Geo& g, const at::Tensor& xsrc, bool batched,
                             const at::Tensor& gy, const at::Tensor& top_left,
                             const at::Tensor& coef) {
  const bool cl = !gy.is_contiguous();  // else channels-last (see backward)
  const SmallKernels small = small_kernels<float>(g);
  const TileKernels<float> kern = tile_kernels<float>(g);
  const int64_t kc = g.K * g.C;
  const BatchTiles bt = batch_tiles(g, small);
  const int64_t chunks =
      std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), bt.tasks));
  at::Tensor gw = at::empty({g.Cout, g.C, g.K}, gy.options());
  at::Tensor rest = at::empty({chunks - 1, g.Cout * kc}, gy.options());
  const auto acc = [&](int64_t chunk) {
    return chunk == 0 ? gw.mutable_data_ptr<float>()
                      : rest.mutable_data_ptr<float>() + (chunk - 1) * g.Cout * kc;
  };
  const float* xp = xsrc.const_data_ptr<float>();
  const float* gp = gy.const_data_ptr<float>();
  const int32_t* tp_left = top_left.const_data_ptr<int32_t>();
  const float* cfp = coef.const_data_ptr<float>();
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    const Uninit<float> cols(g.B * bt.block * kc), ybuf(cl ? 0 : bt.block * g.Cout);
    const int64_t acc_len = kc * g.Cout;
    const Uninit<float> acc_t(acc_len);  // panels, as weight_columns (on a cache line)
    for (int64_t chunk = c0; chunk < c1; ++chunk) {
      std::fill(acc_t.data(), acc_t.data() + acc_len, 0.0f);
      for (int64_t task = chunk * bt.tasks / chunks; task < (chunk + 1) * bt.tasks / chunks;
           ++task) {
        const int64_t pa = task * bt.per_task, pb = std::min(g.P, pa + bt.per_task);
        for (int64_t p0 = pa; p0 < pb; p0 += bt.block) {
          const int64_t m = std::min(bt.block, pb - p0);
          float* cb = cols.data();  // item b's rows: cb + b * m * kc
          if (batched) {
            batch_gather(g, xp, tp_left, cfp, p0, m, cb, m * kc);
          } else {
            for (int64_t b = 0; b < g.B; ++b) {
              kern.gather(g, xp, tp_left, cfp, b, p0, m, cb + b * m * kc);
            }
          }
          for (int64_t b = 0; b < g.B; ++b) {
            const float* yt = rows_of(gp, cl, g.Cout, g.P, b * g.P + p0, m, ybuf.data());
            small.weight_gradient(cb + b * m * kc, m, kc, kc, 0, kc, yt, acc_t.data(), 0, g.Cout);
          }
        }
      }
      panels_to_weight(acc_t.data(), acc(chunk), g.Cout, g.C, g.K);
    }
  });
  if (chunks > 1) {
    sum_chunks<float>(acc, chunks, g.Cout, kc, [&](float* r0, const float* sum) {
      std::copy(sum, sum + kc, r0);
    });
  }
  return gw;
}

at::Tensor forward_batch(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                         const at::Tensor& bias, const at::Tensor& top_left,
                         const at::Tensor& coef, at::MemoryFormat fmt, at::Tensor* padded) {
  const bool cl = fmt == at::MemoryFormat::ChannelsLast;
  const SmallKernels small = small_kernels<float>(g);
  const at::Tensor xq = padded_batch_input(input, g);
  *padded = xq;
  at::Tensor out = at::empty({g.B, g.Cout, g.Ho, g.Wo}, input.options().memory_format(fmt));
  const at::Tensor bias_c = bias.defined() ? bias.contiguous() : bias;
  const float* bp = bias.defined() ? bias_c.const_data_ptr<float>() : nullptr;
  const float* xp = xq.const_data_ptr<float>();
  const int32_t* tp_left = top_left.const_data_ptr<int32_t>();
  const float* cfp = coef.const_data_ptr<float>();
  float* op = out.mutable_data_ptr<float>();
  const int64_t kc = g.K * g.C;
  const at::Tensor wt = weight_columns(weight, g);
  const float* wtp = wt.const_data_ptr<float>();
  const BatchTiles bt = batch_tiles(g, small);
  auto init = [&] {
    return Scratch<float>{Uninit<float>(g.B * bt.block * kc),
                          Uninit<float>(cl ? 0 : bt.block * g.Cout)};
  };
  // Each thread a contiguous range of tasks (at::parallel_for's static split), not tasks handed
  // out as threads come free (parallel_tasks): padded_batch_input split its rows between the
  // threads the same way, so a thread's tasks (output rows) mostly read the padded rows it wrote,
  // from its own L2.
  at::parallel_for(0, bt.tasks, 1, [&](int64_t t0, int64_t t1) {
    Scratch<float> s = init();
    for (int64_t task = t0; task < t1; ++task) {
      const int64_t pa = task * bt.per_task, pb = std::min(g.P, pa + bt.per_task);
      for (int64_t p0 = pa; p0 < pb; p0 += bt.block) {
        const int64_t m = std::min(bt.block, pb - p0);
        float* cb = s.tile.data();  // item b's rows: cb + b * m * kc
        batch_gather(g, xp, tp_left, cfp, p0, m, cb, m * kc);
        for (int64_t b = 0; b < g.B; ++b) {
          float* yp = cl ? op + (b * g.P + p0) * g.Cout : s.y.data();
          small.forward(cb + b * m * kc, m, kc, kc, 0, kc, wtp, bp, yp);
          if (!cl) write_rows(yp, op, false, g.Cout, g.P, b * g.P + p0, m);
        }
      }
    }
  });
  return out;
}

}  // namespace calibconv::native
