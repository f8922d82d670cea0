// The weight (and bias) gradient of calibconv's native deformable convolution: the columns
// gathered again tile by tile and multiplied by the output gradient into per-chunk accumulators.

#include "gather.h"

#include <algorithm>
#include <type_traits>

namespace calibconv::native {

template <typename T>
std::pair<at::Tensor, at::Tensor> grad_weight_impl(const Geo& g, const at::Tensor& input,
                                                   const at::Tensor& gy,
                                                   const at::Tensor& top_left,
                                                   const at::Tensor& coef, const at::Tensor& rows,
                                                   const at::Tensor& kept, bool bias) {
  const bool cl = !gy.is_contiguous();  // else channels-last (see backward)
  // The columns the forward pass kept, or the input to gather them again from (as pad_row reads
  // it: each thread pads the rows it gathers from, PaddedRows).
  const T* kp = kept.defined() ? kept.const_data_ptr<T>() : nullptr;
  const bool direct = !kp && pad_direct(input, g);
  const at::Tensor x = kp ? input : pad_source<T>(input, direct);
  const int32_t* rows_p = rows.const_data_ptr<int32_t>();
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  const int64_t total = g.B * g.P;
  const auto small = small_kernels<T>(g).weight_gradient;
  const bool whole = !small && whole_rows(total, kc, g.Cout * kcg);
  const int64_t tile =
      whole ? std::max<int64_t>(total, 1) : tile_rows(total, kc, g.Cout * kcg, sizeof(T));
  const int64_t tasks = (total + tile - 1) / tile;
  // One accumulator per chunk of tasks; chunks are fixed (not handed out dynamically) so that the
  // summation order, hence the result, is the same on every run with the same thread count.
  // But with several threads, few output channels and a large weight whose panels split evenly
  // between the threads (by_panels), each thread sums the gradient of its own panels over all
  // rows, in their order (as one thread does: the result does not depend on the thread count),
  // gathering every row's columns itself, instead of every output's gradient over its share of
  // the rows (a weight-sized accumulator per thread, zeroed, converted and summed at the end).
  // (Every thread gathers all rows: the condition threads * 32 <= C_out keeps that gather, about
  // 4 reads a value, small against the thread's share of the products, C_out / threads
  // multiply-adds a value; measured at two threads.)
  const int64_t threads = at::get_num_threads();
  const bool by_panels = small && !whole && threads > 1 && kp == nullptr &&
                         small_large_weight(kc, g.Cout) &&
                         (g.Cout / small_panel(g.Cout)) % threads == 0 && threads * 32 <= g.Cout;
  const int64_t chunks =
      whole || by_panels ? 1 : std::max<int64_t>(1, std::min<int64_t>(threads, tasks));
  // Chunk 0 accumulates into the tensor that becomes the result, the others into a buffer freed
  // on return: the peak is `chunks` weights, not `chunks + 1`.
  // (with the few-output-channel kernels every chunk's accumulator is assigned, not added to)
  const auto alloc = [&](at::IntArrayRef size) {
    return small ? at::empty(size, gy.options()) : at::zeros(size, gy.options());
  };
  at::Tensor gw = alloc({g.G, g.Coutg, g.K, g.Cg});
  at::Tensor rest = alloc({chunks - 1, g.G, g.Coutg, g.K, g.Cg});
  T* const gwp = gw.mutable_data_ptr<T>();
  T* const rp = rest.mutable_data_ptr<T>();
  const int64_t wsize = g.G * g.Coutg * kcg;
  const auto acc = [&](int64_t chunk) { return chunk == 0 ? gwp : rp + (chunk - 1) * wsize; };
  // The bias gradient: chunk c's sum in row c of bsum (chunk 0's is the result's).
  const bool with_bias = bias && small;
  at::Tensor bsum = with_bias ? at::empty({chunks, g.Cout}, gy.options()) : at::Tensor();
  T* const bp = with_bias ? bsum.mutable_data_ptr<T>() : nullptr;
  const T* xp = x.const_data_ptr<T>();
  const T* gp = gy.const_data_ptr<T>();
  const int32_t* tp_left = top_left.const_data_ptr<int32_t>();
  const T* cfp = coef.const_data_ptr<T>();
  const TileKernels<T> kern = tile_kernels<T>(g);
  const bool dnn = !small && std::is_same_v<T, float> && g.G == 1 &&
                   g.Cout >= DNN_WEIGHT_MIN_COUT && use_dnn();
  // Rows gathered at a time: a block (few output channels), else the whole tile.
  const int64_t block = small ? small_block_rows(kc, g.Cout, tile) : tile;
  const ColumnSlabs slabs = column_slabs(g, small != nullptr, kp != nullptr);
  // The rows [q0, q0 + n) of the output gradient yt [n, C_out] into the panels acc (as
  // weight_columns), for the outputs [o0, o1), block by block, the columns gathered into cols
  // (or the kept ones read).
  // With b (the bias gradient's accumulator for the outputs [o0, o1); null: none), the rows'
  // output gradients are added to it too.
  const auto small_rows = [&](PaddedRows<T>& src, int64_t q0, int64_t n, const T* yt, T* cols,
                              T* acc, int64_t o0, int64_t o1, T* b) {
    if constexpr (std::is_same_v<T, float>) {
      for (int64_t t0 = 0; t0 < n; t0 += block) {
        const int64_t m = std::min(block, n - t0);
        if (b) {
          for (int64_t t = t0; t < t0 + m; ++t) {
            const T* y = yt + t * g.Cout;
            for (int64_t o = o0; o < o1; ++o) b[o - o0] += y[o];
          }
        }
        if (slabs.on) {
          by_slabs(g, src, tp_left, cfp, q0 + t0, m, cols, slabs.width,
                   [&](int64_t s0, int64_t s1) {
                     small(cols, m, slabs.width, kc, s0, s1, yt + t0 * g.Cout, acc, o0, o1);
                   });
          continue;
        }
        const float* cb = kp ? kp + (q0 + t0) * kc : cols;
        if (!kp) gather_rows(g, kern, src, tp_left, cfp, q0 + t0, m, cols);
        small(cb, m, kc, kc, 0, kc, yt + t0 * g.Cout, acc, o0, o1);
      }
    }
  };
  if (by_panels) {  // a thread's panels over all rows (see by_panels above)
    if constexpr (std::is_same_v<T, float>) {
      const Uninit<float> acc_t(kc * g.Cout);
      at::parallel_for(0, threads, 1, [&](int64_t t0, int64_t t1) {
        const Uninit<T> cols(block * slabs.width), ybuf(cl ? 0 : tile * g.Cout);
        PaddedRows<T> src(g, xp, direct, rows_p);
        for (int64_t t = t0; t < t1; ++t) {
          const int64_t o0 = t * g.Cout / threads, o1 = (t + 1) * g.Cout / threads;
          float* a = acc_t.data() + o0 * kc;  // the range's panels, one after the other
          std::fill(a, a + (o1 - o0) * kc, 0.0f);
          T* bt = with_bias ? bp + o0 : nullptr;  // (one chunk: the result's row)
          if (bt) std::fill(bt, bt + (o1 - o0), T(0));
          for (int64_t q0 = 0; q0 < total; q0 += tile) {
            const int64_t n = std::min(tile, total - q0);
            const T* yt = rows_of(gp, cl, g.Cout, g.P, q0, n, ybuf.data());  // [n, C_out]
            small_rows(src, q0, n, yt, cols.data(), acc_t.data(), o0, o1, bt);
          }
          panels_to_weight(a, gwp + o0 * kc, o1 - o0, g.C, g.K);
        }
      });
      return {gw.view({g.Cout, g.Cg, g.K}), with_bias ? bsum[0] : at::Tensor()};
    }
  }
  const auto body = [&](int64_t c0, int64_t c1) {
    const Uninit<T> cols(kp ? 0 : block * slabs.width), ybuf(cl ? 0 : tile * g.Cout);
    PaddedRows<T> src(g, kp ? nullptr : xp, direct, rows_p);
    // Few output channels: the chunk's sum transposed, [K*C, C_out] as panels (weight_columns),
    // written to its accumulator at the end of the chunk in the final order, [C_out, C, K]
    // (panels_to_weight).
    // (Aligned to a cache line, as Uninit: the kernels read and write it in 64-byte vectors.)
    const int64_t acc_len = small ? kc * g.Cout : 0;
    const Uninit<T> acc_t(acc_len);
    for (int64_t chunk = c0; chunk < c1; ++chunk) {
      T* accp = acc(chunk);
      std::fill(acc_t.data(), acc_t.data() + acc_len, T(0));
      T* bt = with_bias ? bp + chunk * g.Cout : nullptr;
      if (bt) std::fill(bt, bt + g.Cout, T(0));
      for (int64_t task = chunk * tasks / chunks; task < (chunk + 1) * tasks / chunks; ++task) {
        const int64_t q0 = task * tile, n = std::min(tile, total - q0);
        const T* yt = rows_of(gp, cl, g.Cout, g.P, q0, n, ybuf.data());  // [n, C_out]
        if (small) {
          small_rows(src, q0, n, yt, cols.data(), acc_t.data(), 0, g.Cout, bt);
          continue;
        }
        const T* cp = kp ? kp + q0 * kc : cols.data();
        if (!kp) gather_rows(g, kern, src, tp_left, cfp, q0, n, cols.data());
        if constexpr (std::is_same_v<T, float>) {
          if (dnn) {  // acc += (cols^T @ gy)^T: the pixels are the convolution's channels
            const Mat<const float> cols_t{cp, kc, n, 1, kc};
            const Mat<const float> y{yt, n, g.Cout, g.Cout, 1};
            view_of(Mat<float>{accp, g.Cout, kc, kc, 1})
                .add_(dnn_linear(cols_t, view_of(y.t()), at::Tensor()).t());
            continue;
          }
        }
        for (int64_t gi = 0; gi < g.G; ++gi) {
          const Mat<const T> c{cp + gi * kcg, n, kcg, kc, 1};
          const Mat<const T> y{yt + gi * g.Coutg, n, g.Coutg, g.Cout, 1};
          const Mat<T> a{accp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
          gemm<T>(y.t(), c, a, true);
        }
      }
      if constexpr (std::is_same_v<T, float>) {
        // the chunk's sum, [C_out, C, K], is its accumulator
        if (small) panels_to_weight(acc_t.data(), accp, g.Cout, g.C, g.K);
      }
    }
  };
  if (whole) {
    body(0, 1);  // on this thread: the GEMM gets the intra-op threads
  } else {
    at::parallel_for(0, chunks, 1, body);
  }
  // Sum the chunks into chunk 0 and (but for the few-output-channel kernels' accumulators, in
  // that order already) swap (tap, channel) -> (channel, tap) in place, one output channel (a
  // row of K * C/G) at a time: [C_out, C/G, K].
  // (the bias's chunks in their order, into chunk 0's row)
  for (int64_t chunk = 1; with_bias && chunk < chunks; ++chunk) {
    for (int64_t o = 0; o < g.Cout; ++o) bp[o] += bp[chunk * g.Cout + o];
  }
  const at::Tensor gb = with_bias ? bsum[0] : at::Tensor();
  if (small && chunks == 1) return {gw.view({g.Cout, g.Cg, g.K}), gb};
  sum_chunks<T>(acc, chunks, g.Cout, kcg, [&](T* r0, const T* sum) {
    if (small) {
      std::copy(sum, sum + kcg, r0);
      return;
    }
    for (int64_t k = 0; k < g.K; ++k) {
      for (int64_t c = 0; c < g.Cg; ++c) r0[c * g.K + k] = sum[k * g.Cg + c];
    }
  });
  return {gw.view({g.Cout, g.Cg, g.K}), gb};
}
template std::pair<at::Tensor, at::Tensor> grad_weight_impl<float>(
    const Geo&, const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
    const at::Tensor&, const at::Tensor&, bool);
template std::pair<at::Tensor, at::Tensor> grad_weight_impl<double>(
    const Geo&, const at::Tensor&, const at::Tensor&, const at::Tensor&, const at::Tensor&,
    const at::Tensor&, const at::Tensor&, bool);

}  // namespace calibconv::native
