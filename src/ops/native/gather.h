// The sampling side of calibconv's native kernels: the per-sample coefficients, the gather and
// scatter kernels picked per layer (gather.cpp), and the padded input they read (padding.cpp).
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "deform.h"

namespace calibconv::native {

// The per-sample coefficients that the gathers and scatters read (their `coef` argument): the
// plan's fractions (ly, lx), two a sample, from which each sample's four bilinear weights are
// computed where it is gathered or scattered (for every batch item again); or, for the kernels
// of at most CORNER_WEIGHTS_MAX_C channels in one group but 3 (NC 1, 2, 4, 8), the four
// weights themselves, (1 - ly)(1 - lx), (1 - ly) lx, ly (1 - lx) and ly lx, computed once for
// the forward pass and once for the backward (sample_coefficients: the same values, so the same
// bits). At 8 channels a sample is one 32-byte vector a corner and the weights were half its
// instructions; with more channels, or 3, the stream of weights (16 bytes a sample instead of 8)
// cost more than it saved (docs/bench/cpu-kernels.md).
constexpr int64_t CORNER_WEIGHTS_MAX_C = 8;
// (nc: the channel count the kernels are compiled for, 0 for the general ones)
constexpr bool reads_corner_weights(int64_t nc) {
  return nc > 0 && nc <= CORNER_WEIGHTS_MAX_C && nc != 3;
}
constexpr int64_t coef_stride(int64_t nc) { return reads_corner_weights(nc) ? 4 : 2; }
// Sample i's four corner weights, from coef as the kernels of NC channels read it.
template <typename T>
struct Corners {
  T w0, w1, w2, w3;
};
template <typename T, int NC>
CALIBCONV_ALWAYS_INLINE inline Corners<T> corners_at(const T* coef, int64_t i) {
  if constexpr (reads_corner_weights(NC)) {
    const T* w = coef + 4 * i;
    return {w[0], w[1], w[2], w[3]};
  } else {
    const T ly = coef[2 * i], lx = coef[2 * i + 1], hy = 1 - ly, hx = 1 - lx;
    return {hy * hx, hy * lx, ly * hx, ly * lx};
  }
}

// The kernels of one element type, picked by channel count (one group) once per call.
template <typename T>
struct TileKernels {
  using Gather = void (*)(const Geo&, const T*, const int32_t*, const T*, int64_t, int64_t,
                          int64_t, T*);
  using Scatter = void (*)(const Geo&, T*, const int32_t*, const T*, int64_t, int64_t, int64_t,
                           const T*);
  Gather gather;
  Scatter scatter;
  int64_t nc;  // the channel count they are compiled for (0: any)
};
// The gather and scatter of layer g (gather.cpp).
template <typename T>
TileKernels<T> tile_kernels(const Geo& g);
template <>
TileKernels<float> tile_kernels<float>(const Geo& g);
template <>
TileKernels<double> tile_kernels<double>(const Geo& g);

// The coefficients that the kernels of layer g read from the plan's fractions frac [N * 2] (in
// the input's type): the fractions themselves, or where the kernels tile_kernels picks read
// corner weights (reads_corner_weights; batch_gather's 3 channels do not) those weights [N * 4],
// each sample's the same expression as where they are computed from fractions (corners_at).
at::Tensor sample_coefficients(const at::Tensor& frac, const Geo& g);

// The columns [s0, s1) of the rows of output pixels [p0, p0 + n) of batch item b (one group),
// into cols [n, s1 - s0] at row stride ldc: for the few-output-channel kernels' large weights,
// whose forward gathers and multiplies a block's columns one slab at a time (forward_impl). Each
// value is gather_columns_body's expression (the same bits). coef: fractions (such layers have
// more than CORNER_WEIGHTS_MAX_C channels: a weight of SMALL_LARGE_WEIGHT values at 8 channels
// would need over 3000 outputs).
void gather_range_float(const Geo& g, const float* xp, const int32_t* top_left, const float* frac,
                        int64_t b, int64_t p0, int64_t n, int64_t s0, int64_t s1, float* cols,
                        int64_t ldc);

// The columns of output pixels [p0, p0 + n) of every batch item from the padded batch input
// xq (padded_batch_input) into cols + b * ldb (item b's rows of K * 3 values, as
// gather_columns_body writes them): four items a vector of sixteen floats, each lane the same
// expression as gather_sample (the same bits). Each item's sample stores four values, the last
// on the next sample's first, which the call stores later; its last sample stores three.
void batch_gather(const Geo& g, const float* xq, const int32_t* top_left, const float* coef,
                  int64_t p0, int64_t n, float* cols, int64_t ldb);

// ---------------------------------------------------------------------------------------------
// The padded input (padding.cpp).

// Values of slack after the padded input: the gather's vector-of-four loads of 3 channels read
// one value past a pixel.
constexpr int64_t PAD_SLACK = 4;

// Row r of item b of the padded input (see padded_input) into d [Wp, C]: row r - 1 of the
// input from src (channels-last [B, H, W, C], or NCHW where `direct`), or zeros above and below
// it; then its padding columns.
template <typename T>
void pad_row(const Geo& g, const T* src, bool direct, int64_t b, int64_t r, T* d);

// Whether the padding (pad_row) reads the input as NCHW (an image of few channels, transposed in
// the same pass) rather than a channels-last copy.
bool pad_direct(const at::Tensor& input, const Geo& g);

// The lowest and highest input row (-1 to H) that the output rows [oy0, oy1] of plan item `it`
// read (the plan's `rows`, [items, H_out, 2]); lo > hi where they read none.
std::pair<int64_t, int64_t> input_rows(const Geo& g, const int32_t* rows, int64_t it, int64_t oy0,
                                       int64_t oy1);

// The input as the gather reads it: channels-last, padded to [B, H + 3, W + 2, C] (one row above,
// two below, one column on each side; see `padded_size` in ops/plan/mod.rs) with zeros, or with
// Border::WrapX the input's last column in the left padding column and its first in the right;
// then PAD_SLACK zeros. A copy of the input (a few percent of the gather's reads, which are
// 4 * K values a pixel); an NCHW input of few channels (an image) is transposed in the same pass.
// (The first layers of three channels read it; the other gathers pad one item at a time, as
// PaddedRows.)
template <typename T>
at::Tensor padded_input(const at::Tensor& input, const Geo& g);

// First layers gathered for the whole batch at once (batch_gather): float32, 3 channels, one
// plan for every item. The padded input then holds, per padded pixel, every item's channels side
// by side, four values an item (the fourth zero) and the items rounded up to a multiple of four
// (zeros): [H + 3, W + 2, B4, 4] as padded_input's frame (zeros around, or Border::WrapX's
// columns). A sample's corners are then whole vectors of four items (64 bytes), its bilinear
// weights computed once for the batch.
at::Tensor padded_batch_input(const at::Tensor& input, const Geo& g);

// The padded input as one thread's gathers read it, one batch item at a time: a buffer of one
// item's padded frame (and PAD_SLACK zeros), into which the rows that a piece of output pixels
// reads (the plan's `rows`, and the zero rows that samples outside read) are padded when it first
// needs them (pad_row), until a piece of another item comes. Every value a gather reads is the
// value padded_input would hold there (the same bits), but the copy is written to a buffer that
// stays in the caches, not to a batch-sized one that goes out to memory and is read back. Rows
// that no piece reads are never copied; with several threads, rows that two threads' pieces both
// read are copied by both.
template <typename T>
class PaddedRows {
 public:
  // src: the input as pad_row reads it (null: no gathers, no buffer); rows: the plan's
  // [items, H_out, 2] input rows.
  PaddedRows(const Geo& g, const T* src, bool direct, const int32_t* rows)
      : g_(g), src_(src), direct_(direct), rows_(rows), frame_(g.Hp * g.Wp * g.C),
        buf_(src ? frame_ + PAD_SLACK : 0), filled_(src ? g.Hp : 0) {
    if (src) std::fill(buf_.data() + frame_, buf_.data() + frame_ + PAD_SLACK, T(0));
  }
  // The padded input as the gathers take it (xp) for the output pixels [p0, p0 + len) of batch
  // item b, their rows padded: item b's frame is the buffer (the gathers read xp + b * frame on).
  const T* piece(int64_t b, int64_t p0, int64_t len) {
    if (b != item_) {
      item_ = b;
      std::fill(filled_.begin(), filled_.end(), 0);
      ensure(g_.H + 1, g_.H + 2);  // zero rows: the block that samples outside read
    }
    const auto [lo, hi] = input_rows(g_, rows_, g_.item(b), p0 / g_.Wo, (p0 + len - 1) / g_.Wo);
    if (lo <= hi) ensure(lo + 1, hi + 1);  // input rows y are padded rows y + 1
    // (an address computation outside the buffer, as an integer: the gathers add b * frame back)
    return reinterpret_cast<const T*>(reinterpret_cast<uintptr_t>(buf_.data()) -
                                      static_cast<uintptr_t>(b * frame_) * sizeof(T));
  }

 private:
  void ensure(int64_t r0, int64_t r1) {
    for (int64_t r = r0; r <= r1; ++r) {
      if (filled_[r]) continue;
      pad_row(g_, src_, direct_, item_, r, buf_.data() + r * g_.Wp * g_.C);
      filled_[r] = 1;
    }
  }
  const Geo& g_;
  const T* src_;
  bool direct_;
  const int32_t* rows_;
  int64_t frame_;
  Uninit<T> buf_;
  std::vector<uint8_t> filled_;
  int64_t item_ = -1;
};

// Gathers the columns of the flattened rows [q0, q0 + n) (q = b * P + p) into cols [n, K*C],
// piece by piece within batch items (for_items), from the padded input (the thread's PaddedRows).
template <typename T>
void gather_rows(const Geo& g, const TileKernels<T>& kern, PaddedRows<T>& src,
                 const int32_t* top_left, const T* coef, int64_t q0, int64_t n, T* cols) {
  const int64_t kc = g.K * g.C;
  for_items(g.P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
    kern.gather(g, src.piece(b, p0, len), top_left, coef, b, p0, len, cols + off * kc);
  });
}

void gather_range_rows(const Geo& g, PaddedRows<float>& src, const int32_t* top_left,
                       const float* coef, int64_t q0, int64_t n, int64_t s0, int64_t s1,
                       float* cols, int64_t ldc);

// Few output channels with a large weight (blocks of SMALL_LARGE_BLOCK_ROWS rows): the forward
// and the weight gradient gather and multiply a block's columns one slab of SMALL_SLAB at a time,
// the slab in L2, instead of the block's whole rows at once (at 256 -> 256 on 8x8 maps B8, 2.3
// MiB a block, written out to L3 and read back slab by slab). Not with kept columns (a first
// layer's whole column matrix). width: the columns a gathered row holds.
struct ColumnSlabs {
  bool on;
  int64_t width;
};
inline ColumnSlabs column_slabs(const Geo& g, bool small, bool kept) {
  const int64_t kc = g.K * g.C;
  const bool on = small && small_large_weight(kc, g.Cout) && !kept;
  return {on, on ? small_slab_width(kc, g.Cout) : kc};
}

// For column_slabs layers: gathers the slabs of the rows [q0, q0 + m) one after the other into
// cols (rows `width` apart) and calls multiply(s0, s1) on each, the columns [s0, s1).
template <typename F>
void by_slabs(const Geo& g, PaddedRows<float>& src, const int32_t* top_left, const float* coef,
              int64_t q0, int64_t m, float* cols, int64_t width, const F& multiply) {
  const int64_t kc = g.K * g.C;
  for (int64_t s0 = 0; s0 < kc; s0 += SMALL_SLAB) {
    const int64_t s1 = std::min(kc, s0 + SMALL_SLAB);
    gather_range_rows(g, src, top_left, coef, q0, m, s0, s1, cols, width);
    multiply(s0, s1);
  }
}


}  // namespace calibconv::native
