// Shared declarations of calibconv's native CPU kernels (the deformable convolution with fixed
// offsets; design in deform.cpp, the entry point): the layer's geometry, tiling, scratch buffers,
// GEMMs on strided matrices, layout conversions, and the passes each file defines.
#pragma once

// The core Tensor and the few operators used, not <ATen/ATen.h> (every operator's declaration):
// the headers are most of each file's compile time.
#include <ATen/Context.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/addmm.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/from_blob.h>
#include <ATen/ops/mm.h>
#include <ATen/ops/zeros.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <memory>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#include "simd.h"
#include "small_kernels.h"

namespace calibconv::native {

// ---------------------------------------------------------------------------------------------
// Tiling.

// With oneDNN asked for (use_dnn), the weight gradient goes through it from this many output
// channels on (below it oneDNN's reduction over a tile's pixels measured slower than MKL's).
constexpr int64_t DNN_WEIGHT_MIN_COUT = 32;
// The forward pass keeps its column matrix for the weight gradient when the input needs no
// gradient (a first layer) and has at most this many channels (the matrix is then K*C <= 36
// values a pixel, about 9x the input), but for three_channels layers (their batch gather).
constexpr int64_t KEEP_COLUMNS_MAX_C = 4;

// Rows per tile for `total` rows (output pixels of the whole batch, or of one band) of
// `row_elems` elements each, with a weight of `weight_elems` elements. Tiles span batch items
// (the small maps of a U-Net have a few hundred pixels an item: one GEMM per item would be all
// call overhead); small problems get one tile per thread. With several threads the tiles are
// then evened out: their count rounded up to a multiple of the threads, each of about the same
// rows (a multiple of 8), so that no thread is left with a short last tile's worth more work
// than the others.
int64_t tile_rows(int64_t total, int64_t row_elems, int64_t weight_elems, int64_t elem_bytes);

// Whether a pass runs as one tile of all `total` rows on the calling thread, its GEMM then
// parallel inside the BLAS / oneDNN (with the intra-op threads), instead of one tile per thread
// with single-threaded GEMMs: when the weight has at least as many elements as the whole column
// matrix (the deep layers of a wide network on small maps, few pixels and a weight of megabytes),
// every per-thread GEMM would pack the whole weight for a handful of rows. The gather and scatter
// then run on one thread: their cost is proportional to the column matrix, the GEMM's to the
// column matrix times C_out. One thread: always false (nothing to share). Not for the
// few-output-channel kernels when each thread gets at least a block of rows (small_kernels):
// they pack the weight once and multiply tiles of rows on every thread (their weight-gradient
// panels split between the threads, see grad_weight_impl), which is faster.
bool whole_rows(int64_t total, int64_t row_elems, int64_t weight_elems);

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

// Whether the float32 GEMMs of one group go through oneDNN (deform.cpp: only when asked for).
bool use_dnn();

// y = a @ w^T for a [m, kd] (any strides) and w [n, kd] (any strides), through a 1x1 oneDNN
// convolution of the image [1, kd, 1, m] (a's rows are its pixels); bias [n] or undefined.
// Returns y as an [m, n] view of a new tensor (its strides are oneDNN's choice).
at::Tensor dnn_linear(const Mat<const float>& a, const at::Tensor& w, const at::Tensor& bias);

// ---------------------------------------------------------------------------------------------
// Geometry and scheduling.

struct Geo {
  int64_t B, C, H, W, HW, Ho, Wo, P, K, G, Cg, Cout, Coutg;
  // The padded input the gather reads: H + 3 rows, W + 2 columns (`padded_size` in
  // ops/plan/mod.rs).
  int64_t Hp, Wp;
  bool wrap;  // Border::WrapX: the padding columns hold the input's last and first columns
  bool per_item;  // the plan holds one set of samples per batch item
  // Plan item of batch item b.
  int64_t item(int64_t b) const { return per_item ? b : 0; }
};

// Items of padded_batch_input: B rounded up to a multiple of four.
inline int64_t batch_items(int64_t B) { return (B + 3) / 4 * 4; }

// input [B, C, H, W]; a weight [C_out, C/G, kh, kw] with kh * kw = K.
Geo geometry(const at::Tensor& input, int64_t cout, int64_t k, int64_t ho, int64_t wo,
             int64_t groups, bool per_item, bool wrap);

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

// Whether Uninit fills its buffers with NaN (calibconv_native_poison_scratch; the tests turn it
// on): fresh pages are zero, so without it a value read before it was written could go unseen.
extern std::atomic<bool> poison_scratch;

// n values, not initialised: for buffers that every pass writes before it reads them (a
// std::vector zeroes its values first, which showed in profiles of large blocks). Aligned to a
// cache line, as libtorch's tensors: a pixel of 16 float channels in a padded frame is one line,
// not two, and where a buffer begins does not depend on what the process allocated before.
template <typename T>
class Uninit {
 public:
  explicit Uninit(int64_t n) : p_(n > 0 ? allocate(n) : nullptr) {
    if (p_ && poison_scratch.load(std::memory_order_relaxed)) {
      std::fill(p_.get(), p_.get() + n, std::numeric_limits<T>::quiet_NaN());
    }
  }
  T* data() const { return p_.get(); }

 private:
  static constexpr size_t LINE = 64;
  struct Free {
    void operator()(T* p) const { std::free(p); }
  };
  static T* allocate(int64_t n) {
    const size_t bytes = (static_cast<size_t>(n) * sizeof(T) + LINE - 1) / LINE * LINE;
    void* p = std::aligned_alloc(LINE, bytes);
    if (!p) throw std::bad_alloc();
    return static_cast<T*>(p);
  }
  std::unique_ptr<T, Free> p_;
};

// Per-thread buffers: a column tile [T, K*C] and an output-sized tile [T, C_out], each written
// (gathered, multiplied into, or converted into) before it is read.
template <typename T>
struct Scratch {
  Uninit<T> tile, y;
};

// Calls f(b, p0, len, offset) for the pieces of the flattened rows [q0, q0 + n) (q = b * P + p)
// that lie in one batch item each; offset is the piece's first row within the tile.
template <typename F>
void for_items(int64_t P, int64_t q0, int64_t n, const F& f) {
  for (int64_t q = q0; q < q0 + n;) {
    const int64_t b = q / P, p0 = q % P, len = std::min(P - p0, q0 + n - q);
    f(b, p0, len, q - q0);
    q += len;
  }
}

// The rows [q0, q0 + n) of a [B, C, P] tensor (channels-last if cl, else NCHW) as a row-major
// [n, C] matrix: a view for channels-last, else a blocked transpose into buf.
template <typename T>
const T* rows_of(const T* y, bool cl, int64_t C, int64_t P, int64_t q0, int64_t n, T* buf);

// The reverse: writes the row-major [n, C] matrix src into rows [q0, q0 + n) of dst.
template <typename T>
void write_rows(const T* src, T* dst, bool cl, int64_t C, int64_t P, int64_t q0, int64_t n);
// Layout conversions (layout.cpp).

// The input as channels-last-contiguous (a view if it already is).
template <typename T>
at::Tensor channels_last(const at::Tensor& input);
// A channels-last-contiguous tensor as NCHW-contiguous.
template <typename T>
at::Tensor nchw(const at::Tensor& x);
// The layout of the output (and input gradient) for an input: channels-last if the input is
// channels-last (as conv2d), else NCHW.
at::MemoryFormat memory_format(const at::Tensor& input);
// The weight packed as WP [G, C_out/G, K, C/G]: each output channel's [C/G, K] block
// transposed, through convert_pixels for a contiguous weight (8x8 register transposes for
// float), else by a strided copy.
at::Tensor pack_weight(const at::Tensor& weight, const Geo& g);
// The input as pad_row reads it: as it is (made contiguous) where `direct` (pad_direct), else
// channels-last.
template <typename T>
at::Tensor pad_source(const at::Tensor& input, bool direct);

// The weight gradient's chunk accumulators (acc(chunk), `rows` rows of `len` values each, acc(0)
// the result's buffer) summed: per row, in parallel over rows, each value the sum of the chunks'
// in chunk order, handed to finish(acc(0)'s row, the row's sums) to write out.
template <typename T, typename Acc, typename Finish>
void sum_chunks(const Acc& acc, int64_t chunks, int64_t rows, int64_t len, const Finish& finish) {
  at::parallel_for(0, rows, 1, [&](int64_t o0, int64_t o1) {
    std::vector<T> sum(len);
    for (int64_t o = o0; o < o1; ++o) {
      T* r0 = acc(0) + o * len;
      for (int64_t i = 0; i < len; ++i) {
        T s = r0[i];
        for (int64_t chunk = 1; chunk < chunks; ++chunk) s += acc(chunk)[o * len + i];
        sum[i] = s;
      }
      finish(r0, sum.data());
    }
  });
}

// ---------------------------------------------------------------------------------------------
// Few output channels (small.cpp): the deformable convolution's side of small_kernels.h.

// Which library multiplies large weights (calibconv_native_large_weights; see small.cpp).
enum class LargeWeights : int32_t { Auto = 0, Kernels = 1, Blas = 2 };
extern std::atomic<int32_t> large_weights_override;
// Whether large weights go through the BLAS.
bool large_weights_to_blas();
// The few-output-channel kernels (small_kernels.h) of a pass, or all null (small.cpp).
template <typename T>
SmallKernels small_kernels(const Geo& g);
// The float32 weight [C_out, C, kh, kw] of one group as the few-output-channel kernels (float32
// only) multiply it: [K*C, C_out], rows in the columns' (tap, channel) order, stored as panels of
// P = small_panel(C_out) outputs ([C_out / P, K*C, P]), through weight_to_panels: one pass over
// the weight, not a strided copy of a permuted view.
at::Tensor weight_columns(const at::Tensor& weight, const Geo& g);
// Between a float32 weight [C_out, C, K] of one group and its panels [C_out / P, K*C, P].
void weight_to_panels(const float* __restrict w, float* __restrict panels, int64_t Cout, int64_t C,
                      int64_t K);
void panels_to_weight(const float* __restrict panels, float* __restrict w, int64_t Cout, int64_t C,
                      int64_t K);
// Pixels a task and a block of the passes of a whole batch at once (forward_batch,
// grad_weight_first): the rows of tile_rows and small_block_rows, shared by the items.
struct BatchTiles {
  int64_t per_task, block, tasks;
};
BatchTiles batch_tiles(const Geo& g, const SmallKernels& small);
// 3 float channels in one group with the few-output-channel kernels and at least four items: a
// first layer whose forward gathers the whole batch at once (small.cpp).
bool three_channels(const Geo& g, bool is_float);
// The weight gradient of a three_channels first layer, [C_out, C, K]: tasks of output pixels as
// forward_batch, each accumulating, block by block and item by item within a block, into one
// accumulator per chunk of tasks (chunks fixed per thread count, as grad_weight_impl), the
// columns gathered again from xsrc: the padded batch input with one plan (batch_gather), else
// the padded input, item by item (per-item plans; the same values, so the same sums as with one
// plan holding those samples).
at::Tensor grad_weight_first(const Geo& g, const at::Tensor& xsrc, bool batched,
                             const at::Tensor& gy, const at::Tensor& top_left,
                             const at::Tensor& coef);
// forward_impl for three_channels layers with one plan for every item: tasks of output pixels,
// each for every item; per block of pixels the items' columns are gathered at once into the
// thread's buffer (item by item) and each item's block multiplied into its output rows.
// *padded: the padded batch input (a first layer's weight gradient gathers its columns again
// from it, grad_weight_first).
at::Tensor forward_batch(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                         const at::Tensor& bias, const at::Tensor& top_left,
                         const at::Tensor& coef, at::MemoryFormat fmt, at::Tensor* padded);

// ---------------------------------------------------------------------------------------------
// The passes (forward.cpp, grad_weight.cpp, grad_input.cpp), for float and double.

// The output in layout fmt; weight [C_out, C/G, kh, kw] as the caller has it.
template <typename T>
at::Tensor forward_impl(const Geo& g, const at::Tensor& input, const at::Tensor& weight,
                        const at::Tensor& bias, const at::Tensor& top_left,
                        const at::Tensor& coef, const at::Tensor& rows, const at::Tensor& keep,
                        at::MemoryFormat fmt);
// Gradient of the weight, [C_out, C/G, K] (the caller views the kernel dimensions), and, where
// `bias` is asked for and the few-output-channel kernels run, the bias's [C_out] (else
// undefined): the sum of the output gradient's rows, added up block by block as the weight
// gradient reads them (in L1), in the weight gradient's order (its chunks; by_panels: each
// thread its outputs over all rows), instead of a pass of its own over the output gradient
// (`gy.sum`, which reads it from memory).
template <typename T>
std::pair<at::Tensor, at::Tensor> grad_weight_impl(const Geo& g, const at::Tensor& input,
                                                   const at::Tensor& gy,
                                                   const at::Tensor& top_left,
                                                   const at::Tensor& coef, const at::Tensor& rows,
                                                   const at::Tensor& kept, bool bias);
// Input gradient, in the input's memory format.
template <typename T>
at::Tensor grad_input_impl(const Geo& g, const at::Tensor& input, const at::Tensor& wp,
                           const at::Tensor& gy, const at::Tensor& top_left,
                           const at::Tensor& coef, const at::Tensor& rows);

}  // namespace calibconv::native
