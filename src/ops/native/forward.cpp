// The forward pass of calibconv's native deformable convolution: per tile of output pixels, the
// gathered columns times the packed weight (the BLAS, oneDNN or the few-output-channel kernels).

#include "gather.h"

#include <algorithm>
#include <type_traits>

namespace calibconv::native {

template <typename T>
at::Tensor forward_impl(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                        const at::Tensor& bias, const at::Tensor& top_left,
                        const at::Tensor& coef, const at::Tensor& rows, const at::Tensor& keep,
                        at::MemoryFormat fmt) {
  const bool cl = fmt == at::MemoryFormat::ChannelsLast;
  // The input as pad_row reads it (each thread pads the rows it gathers from, PaddedRows).
  const bool direct = pad_direct(input, g);
  const at::Tensor x = pad_source<T>(input, direct);
  const int32_t* rp = rows.const_data_ptr<int32_t>();
  at::Tensor out = at::empty({g.B, g.Cout, g.Ho, g.Wo}, input.options().memory_format(fmt));
  const at::Tensor bias_c = bias.defined() ? bias.contiguous() : bias;
  const T* bp = bias.defined() ? bias_c.const_data_ptr<T>() : nullptr;
  const T* xp = x.const_data_ptr<T>();
  const int32_t* tp_left = top_left.const_data_ptr<int32_t>();
  const T* cfp = coef.const_data_ptr<T>();
  T* op = out.mutable_data_ptr<T>();
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  // Tiles of flattened rows q = b * P + p; per-item plans keep their tiles within one item only
  // in the sense that the gather takes each piece's own samples (for_items).
  const int64_t total = g.B * g.P;
  const SmallKernels small = small_kernels<T>(g);
  const bool whole = !small && whole_rows(total, kc, g.Cout * kcg);
  const int64_t tile =
      whole ? std::max<int64_t>(total, 1) : tile_rows(total, kc, g.Cout * kcg, sizeof(T));
  const int64_t tiles = (total + tile - 1) / tile;
  const TileKernels<T> kern = tile_kernels<T>(g);
  const bool dnn = !small && std::is_same_v<T, float> && g.G == 1 && use_dnn();
  // The weight packed for the products: WP (pack_weight) for the library's GEMMs, or for the
  // few-output-channel kernels weight_columns, straight from the weight (one copy, not WP and
  // then its transpose).
  const at::Tensor wp = small ? at::Tensor() : pack_weight(weight, g);
  const T* wpp = small ? nullptr : wp.const_data_ptr<T>();
  const at::Tensor w2 = small ? at::Tensor() : wp.view({g.Cout, kcg});  // used with G = 1 only
  const at::Tensor wt = small ? weight_columns(weight, g) : at::Tensor();
  // Rows gathered at a time: a block (few output channels), else the whole tile.
  const int64_t block = small ? small_block_rows(kc, g.Cout, tile) : tile;
  // keep (defined): the whole column matrix [B * P, K*C], gathered into it and kept for the
  // weight gradient.
  T* kp = keep.defined() ? keep.mutable_data_ptr<T>() : nullptr;
  const ColumnSlabs slabs = column_slabs(g, static_cast<bool>(small), kp != nullptr);
  struct Local {
    Scratch<T> s;
    PaddedRows<T> src;
  };
  auto init = [&] {
    // (the output tile: not with oneDNN, nor for channels-last output of the small kernels,
    // which write the output's rows directly)
    const int64_t y_rows = dnn || (small && cl) ? 0 : tile;
    return Local{Scratch<T>{Uninit<T>(block * slabs.width), Uninit<T>(y_rows * g.Cout)},
                 PaddedRows<T>(g, xp, direct, rp)};
  };
  const auto body = [&](int64_t task, Local& local) {
    Scratch<T>& s = local.s;
    const int64_t q0 = task * tile, n = std::min(tile, total - q0);
    if constexpr (std::is_same_v<T, float>) {
      if (small) {  // block by block, into the output's rows (channels-last) or a tile of them
        const float* wtp = wt.const_data_ptr<float>();
        float* yp = cl ? op + q0 * g.Cout : s.y.data();
        for (int64_t t0 = 0; t0 < n; t0 += block) {
          const int64_t m = std::min(block, n - t0);
          if (slabs.on) {
            float* cb = s.tile.data();
            by_slabs(g, local.src, tp_left, cfp, q0 + t0, m, cb, slabs.width,
                     [&](int64_t s0, int64_t s1) {
                       small.forward(cb, m, slabs.width, kc, s0, s1, wtp, bp, yp + t0 * g.Cout);
                     });
            continue;
          }
          float* cb = kp ? kp + (q0 + t0) * kc : s.tile.data();
          gather_rows(g, kern, local.src, tp_left, cfp, q0 + t0, m, cb);
          small.forward(cb, m, kc, kc, 0, kc, wtp, bp, yp + t0 * g.Cout);
        }
        if (!cl) write_rows(yp, op, false, g.Cout, g.P, q0, n);
        return;
      }
    }
    T* tp = kp ? kp + q0 * kc : s.tile.data();
    gather_rows(g, kern, local.src, tp_left, cfp, q0, n, tp);
    if constexpr (std::is_same_v<T, float>) {
      if (dnn) {  // y = cols @ W^T + bias, copied into the output's layout
        const Mat<const float> cols{tp, n, kc, kc, 1};
        const at::Tensor y = dnn_linear(cols, w2, bias_c).contiguous();  // [n, C_out]
        write_rows(y.const_data_ptr<float>(), op, cl, g.Cout, g.P, q0, n);
        return;
      }
    }
    T* yp = s.y.data();  // [n, C_out]
    for (int64_t gi = 0; gi < g.G; ++gi) {
      const Mat<const T> cols{tp + gi * kcg, n, kcg, kc, 1};
      const Mat<const T> w{wpp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
      const Mat<T> c{yp + gi * g.Coutg, n, g.Coutg, g.Cout, 1};
      if (bp) {  // c = bias, then c += cols @ w^T
        const T* bg = bp + gi * g.Coutg;
        for (int64_t i = 0; i < n; ++i) std::copy(bg, bg + g.Coutg, c.p + i * c.rs);
      }
      gemm<T>(cols, w.t(), c, bp != nullptr);
    }
    write_rows(yp, op, cl, g.Cout, g.P, q0, n);
  };
  if (whole && total > 0) {
    Local local = init();
    body(0, local);
  } else {
    parallel_tasks(tiles, init, body);
  }
  return out;
}
template at::Tensor forward_impl<float>(const Geo&, const at::Tensor&, const at::Tensor&,
                                     const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                     const at::Tensor&, const at::Tensor&, at::MemoryFormat);
template at::Tensor forward_impl<double>(const Geo&, const at::Tensor&, const at::Tensor&,
                                     const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                     const at::Tensor&, const at::Tensor&, at::MemoryFormat);

}  // namespace calibconv::native
