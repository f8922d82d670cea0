// The input gradient of calibconv's native deformable convolution: per tile the column gradient
// (output gradient times the packed weight), scattered to the corners the samples read, in bands
// of output rows whose input rows are disjoint within each of two phases.

#include "gather.h"

#include <algorithm>
#include <climits>
#include <limits>
#include <type_traits>
#include <vector>

namespace calibconv::native {

// Bands of the scatter: at least BAND_PIXELS output pixels (each band's tiles are GEMMs that
// cost a fixed overhead per call), and enough bands that the batch has MIN_BAND_TASKS of them
// (about eight per phase to hand out to the threads; a batch of 8 gets two bands per item).
constexpr int64_t BAND_PIXELS = 1024;
constexpr int64_t MIN_BAND_TASKS = 16;

// Bands of output rows for the scatter: a band height R such that, within each of the two
// phases (even bands, odd bands), the input rows touched by different bands are disjoint, for
// every plan item. rows holds [items, H_out, 2] (lowest, highest input row read by an output
// row; lowest > highest when it reads none). R starts at the size preferred above and doubles
// until the bands are disjoint; it depends on the shapes and the plan only, never on the thread
// count, so neither does the summation order. Returns R (H_out: one band).
int64_t band_rows(const Geo& g, const int32_t* rows) {
  const int64_t items = g.per_item ? g.B : 1;
  const int64_t bands_wanted =
      std::max<int64_t>(1, (MIN_BAND_TASKS + g.B - 1) / std::max<int64_t>(1, g.B));
  const int64_t preferred =
      std::max((BAND_PIXELS + g.Wo - 1) / g.Wo, (g.Ho + bands_wanted - 1) / bands_wanted);
  for (int64_t r = std::max<int64_t>(1, preferred); r < g.Ho; r *= 2) {
    const int64_t bands = (g.Ho + r - 1) / r;
    bool ok = true;
    for (int64_t it = 0; it < items && ok; ++it) {
      for (int64_t phase = 0; phase < 2 && ok; ++phase) {
        int64_t reach = INT64_MIN;  // highest input row of the earlier bands of this phase
        for (int64_t band = phase; band < bands && ok; band += 2) {
          const auto [lo, hi] =
              input_rows(g, rows, it, band * r, std::min(g.Ho, (band + 1) * r) - 1);
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

// The input gradient as the scatter's tasks build it (grad_input_impl): each task adds into a
// buffer of the padded rows it touches of one batch item at a time (the plan's `rows` of its
// output rows, padded as padded_input), which stays in the caches, and writes them out when it
// is done with the item. A row that only this task touches is final then: its padding columns
// are dropped (Border::WrapX: the right one's additions folded into the first column) and it
// goes to the gradient gx (channels-last [B, H, W, C]). A row that a band of the odd phase
// touches after an even band did is saved whole to a side buffer (`shared`) by the even band and
// loaded from there by the odd one, so every value receives the same additions in the same order
// as in one batch-sized padded buffer (the same bits), without faulting in, zeroing and copying
// out such a buffer.
template <typename T>
class GradientRows {
 public:
  // phases: [items * Hp] bit 0 where an even band of the plan item touches the padded row, bit 1
  // where an odd band does; slot: [items * Hp] the row's index among its item's rows that both
  // phases touch (shared: [B, slots, Wp, C]); rows: the plan's [items, H_out, 2]; max_rows: the
  // most padded rows a task touches in one item.
  GradientRows(const Geo& g, T* gx, T* shared, const uint8_t* phases, const int32_t* slot,
               int64_t slots, const int32_t* rows, int64_t max_rows)
      : g_(g), gx_(gx), shared_(shared), phases_(phases), slot_(slot), slots_(slots),
        rows_(rows), row_(g.Wp * g.C), buf_(max_rows * g.Wp * g.C) {}

  // Starts a task of phase `phase` over the flattened rows [q0, q1).
  void task(int64_t phase, int64_t q0, int64_t q1) {
    phase_ = phase;
    q0_ = q0;
    q1_ = q1;
    item_ = -1;
  }
  // The padded gradient as the scatter takes it (gxp) for a piece of batch item b of the task:
  // rows of b's frame, the rows the task touches held in the buffer (the scatter adds
  // b * frame back).
  T* piece(int64_t b) {
    if (b != item_) {
      finish();
      open(b);
    }
    return reinterpret_cast<T*>(reinterpret_cast<uintptr_t>(buf_.data()) -
                                static_cast<uintptr_t>((b * g_.Hp + r0_) * row_) * sizeof(T));
  }
  // Writes out the rows of the task's last item.
  void finish() {
    if (item_ < 0) return;
    const int64_t it = g_.item(item_), C = g_.C, W = g_.W;
    for (int64_t r = r0_; r <= r1_; ++r) {
      const T* s = buf_.data() + (r - r0_) * row_;
      if (phase_ == 0 && (phases_[it * g_.Hp + r] & 2)) {
        std::copy(s, s + row_, shared_row(r));
        continue;
      }
      if (r < 1 || r > g_.H) continue;  // a padding row
      const T* col0 = s + C;
      T* d = gx_ + ((item_ * g_.H + r - 1) * W) * C;
      std::copy(col0, col0 + W * C, d);
      if (g_.wrap) {
        for (int64_t c = 0; c < C; ++c) d[c] += col0[W * C + c];
      }
    }
    item_ = -1;
  }

 private:
  void open(int64_t b) {
    item_ = b;
    const int64_t it = g_.item(b);
    const int64_t p0 = std::max(q0_, b * g_.P) - b * g_.P;
    const int64_t p1 = std::min(q1_, (b + 1) * g_.P) - b * g_.P;
    const auto [lo, hi] = input_rows(g_, rows_, it, p0 / g_.Wo, (p1 - 1) / g_.Wo);
    r0_ = lo + 1;  // input rows y are padded rows y + 1
    r1_ = hi + 1;
    for (int64_t r = r0_; r <= r1_; ++r) {
      T* d = buf_.data() + (r - r0_) * row_;
      if (phase_ == 1 && (phases_[it * g_.Hp + r] & 1)) {
        const T* s = shared_row(r);
        std::copy(s, s + row_, d);
      } else {
        std::fill(d, d + row_, T(0));
      }
    }
  }
  T* shared_row(int64_t r) const {
    return shared_ + (item_ * slots_ + slot_[g_.item(item_) * g_.Hp + r]) * row_;
  }
  const Geo& g_;
  T* gx_;
  T* shared_;
  const uint8_t* phases_;
  const int32_t* slot_;
  int64_t slots_;
  const int32_t* rows_;
  int64_t row_;
  Uninit<T> buf_;
  int64_t phase_ = 0, q0_ = 0, q1_ = 0, item_ = -1, r0_ = 0, r1_ = -1;
};

// Input gradient, in the input's memory format.
template <typename T>
at::Tensor grad_input_impl(const Geo& g, const at::Tensor& input, const at::Tensor& wp,
                           const at::Tensor& gy, const at::Tensor& top_left,
                           const at::Tensor& coef, const at::Tensor& rows) {
  const bool cl_y = !gy.is_contiguous();  // else channels-last (see backward)
  at::Tensor gx =
      at::empty({g.B, g.C, g.H, g.W}, gy.options().memory_format(at::MemoryFormat::ChannelsLast));
  if (poison_scratch.load(std::memory_order_relaxed)) {
    gx.fill_(std::numeric_limits<T>::quiet_NaN());
  }
  const T* gp = gy.const_data_ptr<T>();
  const T* wpp = wp.const_data_ptr<T>();
  const int32_t* tp_left = top_left.const_data_ptr<int32_t>();
  const T* cfp = coef.const_data_ptr<T>();
  T* gxp = gx.mutable_data_ptr<T>();
  const int64_t kc = g.K * g.C, kcg = g.K * g.Cg;
  const int32_t* rows_p = rows.const_data_ptr<int32_t>();
  const int64_t r = band_rows(g, rows_p);
  const int64_t bands = (g.Ho + r - 1) / r;
  const int64_t band_pixels = std::min(g.P, r * g.Wo);
  // Which phases touch each padded row of each plan item (GradientRows), the slots of the rows
  // that both touch, and the most rows a band touches.
  const int64_t plan_items = g.per_item ? g.B : 1;
  std::vector<uint8_t> phases(plan_items * g.Hp, 0);
  std::vector<int32_t> slot(plan_items * g.Hp, 0);
  int64_t max_rows = 1, slots = 0;
  for (int64_t it = 0; it < plan_items; ++it) {
    for (int64_t band = 0; band < bands; ++band) {
      const auto [lo, hi] =
          input_rows(g, rows_p, it, band * r, std::min(g.Ho, (band + 1) * r) - 1);
      max_rows = std::max(max_rows, hi - lo + 1);
      for (int64_t y = lo; y <= hi; ++y) phases[it * g.Hp + y + 1] |= band % 2 == 0 ? 1 : 2;
    }
    int64_t n = 0;
    for (int64_t row = 0; row < g.Hp; ++row) {
      if (phases[it * g.Hp + row] == 3) slot[it * g.Hp + row] = static_cast<int32_t>(n++);
    }
    slots = std::max(slots, n);
  }
  // Input rows that no band touches get no additions: zeros.
  for (int64_t b = 0; b < g.B; ++b) {
    for (int64_t y = 0; y < g.H; ++y) {
      if (phases[g.item(b) * g.Hp + y + 1] != 0) continue;
      T* d = gxp + (b * g.H + y) * g.W * g.C;
      std::fill(d, d + g.W * g.C, T(0));
    }
  }
  const Uninit<T> shared(g.B * slots * g.Wp * g.C);
  // A task is one band of one item or, with one band per item, whole items (as many as fill a
  // tile, leaving a task per thread): tasks never share an item's band, so the scatter has no
  // race, and every input pixel receives its contributions in output-pixel order whatever the
  // grouping (the grouping may depend on the thread count, the result does not).
  const int64_t threads = at::get_num_threads();
  const int64_t per_task =
      bands > 1 ? 1
                : std::max<int64_t>(1, std::min<int64_t>(BAND_PIXELS / std::max<int64_t>(1, g.P),
                                                         (g.B + threads - 1) / threads));
  const int64_t groups_of_items = (g.B + per_task - 1) / per_task;
  const int64_t tile =
      std::min(tile_rows(g.B * g.P, kc, g.Cout * kcg, sizeof(T)), per_task * band_pixels);
  const TileKernels<T> kern = tile_kernels<T>(g);
  const auto small = small_kernels<T>(g).column_gradient;
  const bool dnn = !small && std::is_same_v<T, float> && g.G == 1 && use_dnn();
  const at::Tensor wt = dnn ? wp.view({g.Cout, kc}).t().contiguous() : at::Tensor();
  // Rows of a column gradient at a time: a block (few output channels), else the whole tile.
  const int64_t block = small ? small_block_rows(kc, g.Cout, tile) : tile;
  const auto gradient_rows = [&] {
    return GradientRows<T>(g, gxp, shared.data(), phases.data(), slot.data(), slots, rows_p,
                           max_rows);
  };
  struct Local {
    Scratch<T> s;
    GradientRows<T> dst;
  };
  auto init = [&] {
    return Local{Scratch<T>{Uninit<T>(block * kc), Uninit<T>(cl_y ? 0 : tile * g.Cout)},
                 gradient_rows()};
  };
  // Rows [first, second) of the flattened (item, pixel) rows of task `task` of phase `phase`.
  const auto task_rows = [&](int64_t phase, int64_t task) {
    const int64_t phase_bands = (bands - phase + 1) / 2;
    const int64_t items = task / phase_bands, band = phase + 2 * (task % phase_bands);
    if (bands > 1) {
      return std::pair<int64_t, int64_t>{items * g.P + band * band_pixels,
                                         items * g.P + std::min(g.P, (band + 1) * band_pixels)};
    }
    return std::pair<int64_t, int64_t>{items * per_task * g.P,
                                       std::min(g.B, (items + 1) * per_task) * g.P};
  };
  // The column gradient gy @ W of the rows whose output gradient is yt [n, C_out]: [n, K*C], in
  // buf or (oneDNN's contiguous result) in hold.
  const auto column_gradient = [&](const T* yt, int64_t n, T* buf, at::Tensor& hold) -> const T* {
    if constexpr (std::is_same_v<T, float>) {
      if (small) {
        small(yt, n, kc, wpp, buf);
        return buf;
      }
      if (dnn) {
        hold = dnn_linear(Mat<const float>{yt, n, g.Cout, g.Cout, 1}, wt, at::Tensor());
        if (hold.is_contiguous()) return hold.const_data_ptr<float>();
        view_of(Mat<float>{buf, n, kc, kc, 1}).copy_(hold);
        return buf;
      }
    }
    for (int64_t gi = 0; gi < g.G; ++gi) {
      const Mat<const T> y{yt + gi * g.Coutg, n, g.Coutg, g.Cout, 1};
      const Mat<const T> w{wpp + gi * g.Coutg * kcg, g.Coutg, kcg, kcg, 1};
      const Mat<T> c{buf + gi * kcg, n, kcg, kc, 1};
      gemm<T>(y, w, c, false);
    }
    return buf;
  };
  // Adds the column gradient src [n, K*C] of rows [q0, q0 + n) (of the task `dst` is on) to the
  // corners they sampled.
  const auto scatter_rows = [&](GradientRows<T>& dst, const T* src, int64_t q0, int64_t n) {
    for_items(g.P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
      kern.scatter(g, dst.piece(b), tp_left, cfp, b, p0, len, src + off * kc);
    });
  };
  const int64_t total = g.B * g.P;
  if (!small && whole_rows(total, kc, g.Cout * kcg) && total > 0) {
    // One GEMM for the column gradient of every row (parallel inside the BLAS / oneDNN), then
    // the scatter on this thread, task by task in the banded order below (the same summation
    // order as the parallel path).
    const Uninit<T> ybuf(cl_y ? 0 : total * g.Cout), cols(total * kc);
    const T* yt = rows_of(gp, cl_y, g.Cout, g.P, 0, total, ybuf.data());  // [total, C_out]
    at::Tensor hold;
    const T* src = column_gradient(yt, total, cols.data(), hold);
    GradientRows<T> dst = gradient_rows();
    for (int64_t phase = 0; phase < 2; ++phase) {
      for (int64_t task = 0; task < groups_of_items * ((bands - phase + 1) / 2); ++task) {
        const auto [q_begin, q_end] = task_rows(phase, task);
        dst.task(phase, q_begin, q_end);
        scatter_rows(dst, src + q_begin * kc, q_begin, q_end - q_begin);
        dst.finish();
      }
    }
  } else {
    for (int64_t phase = 0; phase < 2; ++phase) {
      const int64_t phase_bands = (bands - phase + 1) / 2;
      parallel_tasks(groups_of_items * phase_bands, init, [&](int64_t task, Local& local) {
        Scratch<T>& s = local.s;
        const auto [q_begin, q_end] = task_rows(phase, task);
        local.dst.task(phase, q_begin, q_end);
        for (int64_t q0 = q_begin; q0 < q_end; q0 += tile) {
          const int64_t n = std::min(tile, q_end - q0);
          const T* yt = rows_of(gp, cl_y, g.Cout, g.P, q0, n, s.y.data());  // [n, C_out]
          for (int64_t t0 = 0; t0 < n; t0 += block) {
            const int64_t m = std::min(block, n - t0);
            at::Tensor hold;
            scatter_rows(local.dst, column_gradient(yt + t0 * g.Cout, m, s.tile.data(), hold),
                         q0 + t0, m);
          }
        }
        local.dst.finish();
      });
    }
  }
  if (memory_format(input) == at::MemoryFormat::ChannelsLast) return gx;
  return nchw<T>(gx);
}
template at::Tensor grad_input_impl<float>(const Geo&, const at::Tensor&, const at::Tensor&,
                                        const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                        const at::Tensor&);
template at::Tensor grad_input_impl<double>(const Geo&, const at::Tensor&, const at::Tensor&,
                                        const at::Tensor&, const at::Tensor&, const at::Tensor&,
                                        const at::Tensor&);

}  // namespace calibconv::native
