// The few-output-channel products (small_kernels.h) in the deformable convolution: which passes
// take them, the weight in panels, and the first layers of 3 channels that gather the whole batch
// at once (forward_batch, grad_weight_first).

#include "gather.h"

#include <algorithm>
#include <type_traits>

namespace calibconv::native {

// Which library multiplies large weights (more than BLAS_WEIGHT values, 4 MiB: from
// 256->512 and 512->256 on) where the few-output-channel kernels exist: 0 the CPU's default, 1
// the kernels, 2 the BLAS (calibconv_native_large_weights; `calibconv bench --large-weights`).
// The default is the BLAS where it is MKL on an Intel CPU, the kernels elsewhere. MKL runs its
// AVX-512 code on Intel CPUs only (on AMD ones its AVX2 code, which the kernels beat at every
// shape measured, see small_kernels.h); on an Intel Xeon with AVX-512 and AMX (2 cores, 48 KiB L1
// and 2 MiB L2 each, one thread, calibrated / conv2d forward and f+b, one process per choice)
// its column and weight gradients beat the kernels' at every large weight measured, kernels ->
// BLAS for both gradients: 1024->1024 at 16x16 B2 f+b 1.72 -> 1.10x, 1024->512 at 32x32 B2
// 1.79 -> 1.07x, 512->512 1.23 -> 1.04x, 256->256 at 64x64 B2 1.50 -> 1.07x, 256->128 at 16x16
// B8 1.51 -> 1.21x, 256->256 at 8x8 B8 1.23 -> 1.15x, 128->256 at 8x8 1.22 -> 1.15x; its
// forward beat the kernels' from weights of 4 MiB (BLAS_WEIGHT) on (1024->1024 1.23 ->
// 1.03x, 1024->512 1.39 -> 1.22x, 512->512 1.30 -> 1.22x) but not below (256->256 at 8x8 1.25
// -> 1.26x, 128->256 1.16 -> 1.20x). Smaller weights keep the kernels there too (64->64 at 32x32
// B8 forward 1.24x against 1.34x through MKL, 32->16 at 128x128 1.41x against 1.72x). Once the
// kernels' register blocks were sized for this Xeon (seventeenth session, small_kernels.h), their
// forward beat MKL's at weights over 4 MiB too where a pass has BLAS_FORWARD_MIN_ROWS rows or
// more (BLAS -> kernels, two processes: 256->512 at 32x32 B2 1.18-1.19 -> 1.10x, 512->512
// 1.19-1.22 -> 1.14x, 1024->512 1.24-1.25 -> 1.19-1.21x, 512->256 at 64x64 B2 1.28-1.29 ->
// 1.14-1.15x) but not with fewer (1024->1024 at 16x16 B2, 512 rows, 1.02-1.03 -> 1.07x); the
// gradients stay MKL's (through the kernels 1024->512 f+b 1.05 -> 1.79-1.81x). Once the loop
// over k of the kernels' products ran four steps an iteration (twentieth session, tile_product),
// their gradients beat MKL's at weights of 1-4 MiB, where they had gone to MKL since the
// fourteenth session (MKL -> kernels, two processes alternating, f+b: one thread 128->256 at 8x8
// B8 1.11-1.13 -> 1.03-1.04x, 256->128 at 16x16 1.14-1.15 -> 1.10-1.13x, 256->256 at 8x8 1.11 ->
// 1.11-1.12x, 128->256 at 64x64 B2 1.01 -> 0.97-0.98x, 256->128 at 128x128 1.00-1.01 ->
// 0.98-1.00x, 256->256 at 64x64 1.01-1.03 -> 1.04-1.05x; two threads 256->256 at 8x8 1.19-1.20 ->
// 1.15x, 128->256 1.10-1.12 -> 1.02x): BLAS_WEIGHT. Above 4 MiB MKL's stay far ahead
// (512->512 at 32x32 B2 1.00 -> 1.28x, 1024->1024 at 16x16 1.06 -> 1.67x).
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
// BLAS's multithreaded products, as all of them did before the panel split (one tile per thread
// gave each a weight-sized gradient accumulator: 1024->1024 on 16x16 maps, B2, two threads, f+b
// 1.41-1.49x conv2d, against 1.26-1.29x through the BLAS then; see whole_rows for now).
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
// P contiguous values, at once. (Before: 8 outputs' rows transposed into a [K*C, 8] buffer, then
// copied row by row into the panels, 32 bytes of a 256-byte row each time: at 256 -> 256
// channels on 8x8 maps B8, 6.3% of the forward's perf samples, 5.0-5.3% now. Through an L1
// buffer of 8 channels' rows, copied out to the panels 8 rows a tap: 7.4-7.7%, its copies calls
// to memmove.) C_out is a multiple of 8.
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
  // Panels in parallel (the pass runs before the tiles' parallel loop, on one thread it left the
  // others waiting: 256->256 at 8x8 B8, two threads, forward 4.02 -> 3.86 ms, medians of 300
  // calls alternating in one process).
  at::parallel_for(0, g.Cout / P, 1, [&](int64_t p0, int64_t p1) {
    weight_to_panels(w + p0 * P * kc, d + p0 * P * kc, (p1 - p0) * P, g.C, g.K);
  });
  return wt;
}

// An item's block is a multiple of the forward kernel's rows at a time (small.rows): the kernels
// are called once per item and block, and a row left over is multiplied alone, one dependent
// multiply-add after the other. (Before: 144 rows / 8 items = 18, with 12 rows at a time 12 + 4
// + 1 + 1; now 24. One thread, Intel Xeon, 3 processes each way alternating, calibrated /
// conv2d forward: 3->16 at 128x128 B8 1.35-1.39 -> 1.22-1.24x, at 144x160 1.31-1.38 -> 1.25x,
// 3->8 at 64x64 1.01-1.06 -> 0.90-0.93x; f+b 1.16-1.18 -> 1.11-1.15x, 1.21-1.23 -> 1.19-1.20x.
// The forward's values did not change; the weight gradient (grad_weight_first) adds its rows
// block by block, item by item, so its sums changed order: other rounding.)
BatchTiles batch_tiles(const Geo& g, const SmallKernels& small) {
  const int64_t kc = g.K * g.C;
  const int64_t tile = tile_rows(g.B * g.P, kc, g.Cout * kc, sizeof(float));
  const int64_t per_task = std::max<int64_t>(1, tile / g.B);
  const int64_t r = std::max<int64_t>(1, small.rows);
  const int64_t per_item = std::max<int64_t>(1, small_block_rows(kc, g.Cout, tile) / g.B);
  return {per_task, (per_item + r - 1) / r * r, (g.P + per_task - 1) / per_task};
}

// 3 float channels (an RGB image: a first layer) in one group, with the few-output-channel kernels
// and at least four items (fewer leave the vectors of four items partly empty: at 3->64 on 256x256
// maps B2 the batch path's f+b was 3-5% slower, 2 processes). With one plan for every item the
// forward pass gathers the whole batch at once (padded_batch_input, batch_gather); as a first layer
// (the input needs no gradient) its weight gradient goes through pixel blocks of all items
// (grad_weight_first), the columns gathered again rather than kept (the kept column matrix, 9
// values a pixel for every value of the input, was written to memory in the forward pass and read
// back in the backward: that writing bound the gather). In one process alternating with the
// kept-columns path (one thread, Zen 4, F195 plans, medians of 200-400 calls, 2-3 processes):
// forward 3->16 at 128x128 B8 4.16-4.73 -> 3.56-3.91 ms, 3->8 at 64x64 B8 0.62-0.64 -> 0.52-0.54
// ms, forward+backward 10.0-10.9 -> 10.0-10.7 ms and 1.23-1.56 -> 1.25-1.48 ms; peak memory of a
// training step of the layer (`calibconv bench --first-layer`) 29.4 -> 18.0 MiB at 3->16 128x128 B8
// (conv2d 16.0).
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
  // from its own L2. (tiny's first layer, 3->8 at 64x64 B8, two threads, forward: the tasks took
  // 322 us a call handed out, 280 us in ranges; with pad_batch_row, calibrated / conv2d 1.29-1.34
  // -> 1.08-1.10x, docs/bench/twenty-first-session-ab.txt.)
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
