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
//   per tile, compiled per instruction-set level (AVX-512, AVX2) and picked at run time; see
//   "Few output channels".
//
// The instruction-set helpers are in simd.h, the few-output-channel kernels in small_kernels.h.
// Tiles run in parallel with at::parallel_for. The entry point catches every C++ exception and
// returns its message: no exception crosses into Rust.

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <ATen/ops/mkldnn_convolution.h>
#include <torch/csrc/autograd/custom_function.h>

#include <algorithm>
#include <atomic>
#include <climits>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <new>
#include <string>
#include <type_traits>
#include <vector>

#include "simd.h"
#include "small_kernels.h"

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
// Rows of a tile: enough that its GEMM does at least MIN_TILE_FLOP (a oneDNN call costs ~15 us,
// about 3 MFLOP of work: few channels need thousands of rows, 512 a few dozen), at least
// MIN_TILE, at most MAX_TILE.
constexpr int64_t MIN_TILE_FLOP = 8 << 20;
constexpr int64_t MIN_TILE = 64;
constexpr int64_t MAX_TILE = 8192;
// With oneDNN asked for (use_dnn), the weight gradient goes through it from this many output
// channels on (below it oneDNN's reduction over a tile's pixels was slower than MKL's: 40 vs 69
// GFLOP/s at 8 channels, even at 16, 1.5-1.7x faster from 32 on; Zen 5).
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
// than the others. (Before: 256->256 at 8x8 B8, 512 rows, made tiles of 224, 224 and 64 rows,
// one thread doing 288 rows while the other waited; two threads, forward medians of 300 calls
// alternating in one process, 4.13 -> 3.86 ms and 4.04 -> 3.73 ms.) One thread: as before.
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

// Whether a pass runs as one tile of all `total` rows on the calling thread, its GEMM then
// parallel inside the BLAS / oneDNN (with the intra-op threads), instead of one tile per thread
// with single-threaded GEMMs: when the weight has at least as many elements as the whole column
// matrix (the deep layers of a wide network on small maps, few pixels and a weight of megabytes),
// every per-thread GEMM would pack the whole weight for a handful of rows. The gather and scatter
// then run on one thread: their cost is proportional to the column matrix, the GEMM's to the
// column matrix times C_out. One thread: always false (nothing to share). Not for the
// few-output-channel kernels when each thread gets at least a block of rows (small_kernels):
// they pack the weight once and multiply tiles of rows on every thread (their weight-gradient
// panels split between the threads, see grad_weight_impl): classic 512->1024 and 1024->1024 at
// 16x16 B2, two threads, calibrated / conv2d forward 1.27-1.46x through the BLAS's threads ->
// 0.94-1.08x, f+b 1.18-1.48x -> 1.06-1.07x (2 rounds alternating).
bool whole_rows(int64_t total, int64_t row_elems, int64_t weight_elems) {
  return at::get_num_threads() > 1 && weight_elems >= total * row_elems;
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

// float32 GEMMs of one group (G = 1) that the few-output-channel kernels do not take go through the
// BLAS (at::mm, libtorch's MKL) by default, or through oneDNN as a 1x1 convolution
// (at::mkldnn_convolution) when asked (calibconv_native_gemm; `calibconv bench --gemm`, for A/B
// timings). These are the layers of more than 1024 outputs or a weight of more than 36 MiB (more
// than 32 outputs on CPUs without AVX-512), and the weight gradient from DNN_WEIGHT_MIN_COUT
// outputs where no few-output-channel kernel exists. oneDNN was the default on CPUs with AVX-512
// while it also multiplied the few-channel layers (there, on an AMD EPYC Zen 5, it reached 140-240
// GFLOP/s where MKL's AVX2 code reached 80-110); once those had their own kernels, the BLAS
// measured faster at the shapes left, on both CPUs compared (one thread, interleaved, calibrated /
// conv2d forward and f+b, oneDNN -> the BLAS): an AMD EPYC Zen 3 without AVX-512, 1024->1024 at
// 16x16 B2 2.87 / 1.86x -> 1.00 / 1.18x, 512->512 at 32x32 1.16 / 1.44x -> 1.10 / 1.17x, 256->256
// at 8x8 B8 1.09 / 1.44x -> 0.95 / 1.06x; an AMD EPYC Zen 4 with AVX-512 (2 rounds each), 256->256
// at 8x8 B8 2.08-2.15 / 2.16-2.61x -> 1.38-1.42 / 1.39x, 128->256 at 8x8 B8 1.64-2.17 / 2.29-2.33x
// -> 1.42-1.48 / 1.36-1.37x, 1024->1024 at 16x16 B2 1.32-1.40 / 1.34-1.42x -> 1.19-1.21 /
// 1.06-1.31x, and no row of ten (128-1024 channels, 8x8-64x64) slower in both rounds. oneDNN also
// reorders the weight on every call: its layers' peak memory was 0.8-3.2x conv2d's against 0.7-1.7x
// with the BLAS (Zen 4). Float64 (which oneDNN does not have) and grouped convolutions always use
// at::mm.
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

// y = a @ w^T for a [m, kd] (any strides) and w [n, kd] (any strides), through a 1x1 oneDNN
// convolution of the image [1, kd, 1, m] (a's rows are its pixels); bias [n] or undefined.
// Returns y as an [m, n] view of a new tensor (its strides are oneDNN's choice).
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

// ---------------------------------------------------------------------------------------------
// Geometry and scheduling.

struct Geo {
  int64_t B, C, H, W, HW, Ho, Wo, P, K, G, Cg, Cout, Coutg;
  // The padded input the gather reads: H + 3 rows, W + 2 columns (plan.rs, `padded_size`).
  int64_t Hp, Wp;
  bool wrap;  // Border::WrapX: the padding columns hold the input's last and first columns
  bool per_item;  // the plan holds one set of samples per batch item
  // Plan item of batch item b.
  int64_t item(int64_t b) const { return per_item ? b : 0; }
};

// Items of padded_batch_input: B rounded up to a multiple of four.
int64_t batch_items(int64_t B) { return (B + 3) / 4 * 4; }

// input [B, C, H, W]; a weight [C_out, C/G, kh, kw] with kh * kw = K.
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
std::atomic<bool> poison_scratch{false};

// n values, not initialised: for buffers that every pass writes before it reads them (a
// std::vector zeroes its values first: at 256 -> 256 channels on 8x8 maps a block of columns is
// 2.3 MiB, and the zeroing was 1.5-2% of a forward + backward's samples in perf). Aligned to a
// cache line, as libtorch's tensors: a pixel of 16 float channels in a padded frame is one line,
// not two. (With malloc's 16 bytes, where a buffer began depended on what the process had
// allocated and freed before: at 16 -> 16 channels on 128x128 maps B8 the same gathers took
// 9% or 13% of a forward + backward's perf samples from one build to the next.)
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

// Output matrix of group gi for output pixels [p0, p0 + n) of item b: [n, C_out/G], in the
// output's layout (channels-last rows, or NCHW columns).
template <typename T>
Mat<T> out_block(const Geo& g, T* out, bool cl, int64_t b, int64_t gi, int64_t p0, int64_t n) {
  return cl ? Mat<T>{out + (b * g.P + p0) * g.Cout + gi * g.Coutg, n, g.Coutg, g.Cout, 1}
            : Mat<T>{out + (b * g.Cout + gi * g.Coutg) * g.P + p0, n, g.Coutg, 1, g.P};
}

// The per-sample coefficients that the gathers and scatters read (their `coef` argument): the
// plan's fractions (ly, lx), two a sample, from which each sample's four bilinear weights are
// computed where it is gathered or scattered (for every batch item again); or, for the kernels
// of at most CORNER_WEIGHTS_MAX_C channels in one group but 3 (NC 1, 2, 4, 8), the four
// weights themselves, (1 - ly)(1 - lx), (1 - ly) lx, ly (1 - lx) and ly lx, computed once for
// the forward pass and once for the backward (sample_coefficients: the same values, so the same
// bits). At 8 channels a sample is one 32-byte vector a corner, and the weights were half its
// instructions: with them from memory (F195 plans, one thread, Intel Xeon) the forward's gather
// of 8->8 at 64x64 B8 took 1.32-1.34 -> 1.01-1.03 M TSC cycles a call (rdtsc), and calibrated /
// conv2d went 1.31-1.36 -> 1.19-1.23x forward, 1.06-1.10 -> 0.99-1.03x f+b (3 processes each).
// With more channels the stream of weights (16 bytes a sample instead of 8) cost more than it
// saved: the gather of 16->16 at 128x128 7.9-8.5 -> 9.4 M cycles a call, of 64->32 at 64x64 5.6
// -> 6.1-6.3 M; with 3 channels (first layers, whose gathers take two samples a vector or four
// items a vector) 3->8 at 64x64 forward 1.06-1.12 -> 1.12-1.14x. (The scatter alone with them
// at 16 and 32 channels: no change.)
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

// The gather of the columns of output pixels [p0, p0 + n) of batch item b into cols [n, K*C]
// (layout: group, tap, channel within the group) from the padded channels-last input xp
// (padded_input): a sample's corners are t, t + 1, t + Wp, t + Wp + 1 from its top-left corner t
// (the plan's top_left; plan.rs says why every corner, inside or not, is a real pixel of the
// padded input), each weighted by its bilinear weight: one index load per sample, no selects.
// Against the plan's four corner indices into the unpadded input, each with a select for
// out-of-range corners (the gather before this one, which staged the addresses of 64 samples at
// a time), in one C++ process (float32, F195 plans, B8, one thread, Zen 3, the padding copy
// included): 3 channels at 64x64 and 128x128 0.56-0.62x, 8 channels 0.67-0.77x, 16 channels
// 0.74-0.81x; the same bits (each value is the same expression of the same numbers).
// NC > 0 fixes the channel count at compile time (one group): at 3-64 channels a sample is a few
// vector operations, so the channel loop must be unrolled and vectorised for the instruction set
// (the callers below are multiversioned; this body is inlined into every clone). Three channels
// (a first layer's RGB) go through vectors of four: each corner load also reads the next pixel's
// first channel (the padded input ends with slack for it), and each sample's store writes one
// value past its row, which the next sample's store overwrites; the call's last sample stores its
// three values alone (the values after it belong to another call, maybe another thread's).
template <typename T, int NC>
constexpr int gather_lanes() {
  constexpr int L = NC == 3 ? 4 : NC;
  if constexpr (NC >= 3 && VecOf<T, L>::ok) return L;
  return 0;
}

// Lanes of the vectors that the gather and the scatter of NC channels compute with: NC (4 for
// 3), at most 32 bytes. Wider channel vectors go in chunks of 32 bytes: GCC 12 lowers a store
// of a vector wider than the clone's registers, inside these loops, through the stack (spills,
// general-register moves, four 16-byte stores that read back across two 32-byte writes, a
// store-forwarding stall); in 32-byte chunks it is two plain stores (the same values: each lane
// is the same expression). In one C++ process (16 float channels, F195 plans, B8, one thread,
// AVX2) the chunked gather took 0.82-0.88x the time of the one with whole 64-byte vectors.
template <typename T, int NC>
constexpr int chunk_lanes() {
  constexpr int L = NC == 3 ? 4 : NC, most = static_cast<int>(32 / sizeof(T));
  return L < most ? L : most;
}

// Sample i's value: its four corners (from its top-left corner a, `down` values a padded row),
// weighted and summed (one expression for the samples stored whole and the call's last sample of
// 3 channels, stored value by value; an always-inlined template takes its caller's clone's
// instruction set).
template <typename V, typename T, int NC>
CALIBCONV_ALWAYS_INLINE inline V gather_sample(const T* xb, const int32_t* tl, const T* coef,
                                               int64_t down, int64_t i, int c0) {
  const Corners<T> w = corners_at<T, NC>(coef, i);
  const T* a = xb + int64_t{tl[i]} * NC + c0;
  return w.w0 * load<V>(a) + w.w1 * load<V>(a + NC) + w.w2 * load<V>(a + down) +
         w.w3 * load<V>(a + down + NC);
}

// The samples [0, i) of a 3-channel float gather, four at a time, returned i (the rest, at least
// one sample, goes one at a time: see gather_columns_body). Two samples share a vector of eight
// floats (each in four lanes, as one sample's vector of four in the loop one at a time), so
// every weight, product and sum is computed once for two samples; the bilinear weights of four
// samples come from one load of their fractions, spread to the lanes by a shuffle. Each lane
// computes the same expression of the same values as the loop one at a time (the same bits).
// A pair's six values are packed and stored as eight: the last two land on the next sample's
// first values, which this call stores later (hence i + 4 < count). Against the loop one at a
// time (F195 plans, B8, one thread, Zen 4): the forward of 3->16 at 128x128 into an L1 block
// 3.35-3.41 -> 3.09-3.22 ms (medians of 300 calls, page faults kept out); `calibconv bench
// --first-layer`, calibrated / conv2d forward, 3 rounds: 3->16 at 128x128 1.71-1.79 ->
// 1.56-1.74x, at 144x160 1.77-1.95 -> 1.67-1.76x (its columns, kept for the weight gradient,
// are written to memory: the stores, not the arithmetic, bound it there).
CALIBCONV_ALWAYS_INLINE inline int64_t gather3_quads(const float* xb, const int32_t* tl,
                                                    const float* f, int64_t down, int64_t count,
                                                    float* cols) {
  using V8 = VecOf<float, 8>::type;
  using V4 = VecOf<float, 4>::type;
  using I8 = VecOf<int32_t, 8>::type;
  constexpr int NC = 3;
  int64_t i = 0;
  static_assert(!reads_corner_weights(NC));
  for (; i + 4 < count; i += 4) {
    const V8 fr = load<V8>(f + 2 * i);
    for (int h = 0; h < 2; ++h) {
      const int64_t s = i + 2 * h;
      const V8 ly = h == 0 ? __builtin_shuffle(fr, I8{0, 0, 0, 0, 2, 2, 2, 2})
                           : __builtin_shuffle(fr, I8{4, 4, 4, 4, 6, 6, 6, 6});
      const V8 lx = h == 0 ? __builtin_shuffle(fr, I8{1, 1, 1, 1, 3, 3, 3, 3})
                           : __builtin_shuffle(fr, I8{5, 5, 5, 5, 7, 7, 7, 7});
      const V8 hy = 1 - ly, hx = 1 - lx;
      const float* a0 = xb + int64_t{tl[s]} * NC;
      const float* a1 = xb + int64_t{tl[s + 1]} * NC;
      const auto both = [&](int64_t o) {
        return __builtin_shufflevector(load<V4>(a0 + o), load<V4>(a1 + o), 0, 1, 2, 3, 4, 5, 6, 7);
      };
      const V8 v = (hy * hx) * both(0) + (hy * lx) * both(NC) + (ly * hx) * both(down) +
                   (ly * lx) * both(down + NC);
      store(cols + s * NC, __builtin_shuffle(v, I8{0, 1, 2, 4, 5, 6, 7, 7}));
    }
  }
  return i;
}

// A sample's bilinear weights and its four corners (from its top-left corner tl[i], C values a
// pixel, `down` values a padded row), and its values of n channels from channel o on: the
// expression of every gather of one channel at a time (the vectorised paths compute the same
// expression on vectors).
template <typename T>
struct Sample {
  T w0, w1, w2, w3;
  const T *a0, *a1, *a2, *a3;
};
template <typename T, int NC>
CALIBCONV_ALWAYS_INLINE inline Sample<T> sample_at(const T* xb, const int32_t* tl, const T* coef,
                                                   int64_t i, int64_t C, int64_t down) {
  const Corners<T> w = corners_at<T, NC>(coef, i);
  const T* a0 = xb + int64_t{tl[i]} * C;
  return {w.w0, w.w1, w.w2, w.w3, a0, a0 + C, a0 + down, a0 + down + C};
}
template <typename T>
CALIBCONV_ALWAYS_INLINE inline void sample_channels(const Sample<T>& s, int64_t o, int64_t n,
                                                    T* __restrict dst) {
  const T *__restrict a0 = s.a0 + o, *__restrict a1 = s.a1 + o, *__restrict a2 = s.a2 + o,
                     *__restrict a3 = s.a3 + o;
  CALIBCONV_IVDEP
  for (int64_t c = 0; c < n; ++c) {
    dst[c] = s.w0 * a0[c] + s.w1 * a1[c] + s.w2 * a2[c] + s.w3 * a3[c];
  }
}

// Whether the gather and scatter of NC channels in chunks of CLW lanes compute the samples'
// bilinear weights first, WEIGHT_CHUNK samples at a time into an L1 buffer (corner_weights), and
// then read each weight from there as a broadcast operand: the 64-byte variants of 16 float
// channels and more (AVX-512, tile_kernels). Computed per sample, the weights are six scalar
// operations and four broadcasts from registers, and with 512-bit operations in flight (which leave
// the vector units of two ports to them) those ten take the ports that the sample's four
// multiply-adds need; from memory a broadcast is a load. Standalone (16 channels, 24-pixel blocks
// of a 128x128 map, one thread, Intel Xeon, TSC cycles a sample): gather 4.7-4.9 -> 3.6-4.0,
// scatter 6.3-7.1 -> 5.9-6.4. Each weight is the same expression (the same bits).
constexpr int64_t WEIGHT_CHUNK = 64;
template <typename T, int NC, int CLW>
constexpr bool weights_first() {
  return std::is_same_v<T, float> && NC >= 16 && CLW == 16 && !reads_corner_weights(NC);
}

// The four bilinear weights of samples [0, m) (m <= WEIGHT_CHUNK) from their fractions f (two a
// sample), into w[c * WEIGHT_CHUNK + i] for corner c: corners_at's expressions, sixteen samples
// a vector (the fractions de-interleaved by a shuffle), the rest one at a time.
CALIBCONV_ALWAYS_INLINE inline void corner_weights(const float* __restrict f, int64_t m,
                                                   float* __restrict w) {
  using V = VecOf<float, 16>::type;
  using I = VecOf<int32_t, 16>::type;
  int64_t i = 0;
  for (; i + 16 <= m; i += 16) {
    const V a = load<V>(f + 2 * i), b = load<V>(f + 2 * i + 16);
    constexpr I even{0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30};
    const V ly = __builtin_shuffle(a, b, even), lx = __builtin_shuffle(a, b, even + 1);
    const V hy = 1 - ly, hx = 1 - lx;
    store(w + i, hy * hx);
    store(w + WEIGHT_CHUNK + i, hy * lx);
    store(w + 2 * WEIGHT_CHUNK + i, ly * hx);
    store(w + 3 * WEIGHT_CHUNK + i, ly * lx);
  }
  for (; i < m; ++i) {
    const Corners<float> c = corners_at<float, 16>(f, i);
    w[i] = c.w0;
    w[WEIGHT_CHUNK + i] = c.w1;
    w[2 * WEIGHT_CHUNK + i] = c.w2;
    w[3 * WEIGHT_CHUNK + i] = c.w3;
  }
}

template <typename T, int NC, int CLW = chunk_lanes<T, NC>()>
CALIBCONV_ALWAYS_INLINE inline void gather_columns_body(const Geo& g, const T* xp,
                                                        const int32_t* top_left, const T* coef,
                                                        int64_t b, int64_t p0, int64_t n,
                                                        T* cols) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;  // per-item plans index the stacked padded items
  const int64_t C = NC > 0 ? NC : g.C, Cg = NC > 0 ? NC : g.Cg, G = NC > 0 ? 1 : g.G;
  const int64_t K = g.K, down = g.Wp * C;
  const T* xb = xp + (b * frame - shift) * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const T* __restrict f = coef + coef_stride(NC) * s_begin;
  if constexpr (NC > 0 && gather_lanes<T, NC>() > 0) {
    // One group: the columns are the samples' rows back to back.
    constexpr int L = gather_lanes<T, NC>(), CL = CLW;
    using V = typename VecOf<T, CL>::type;
    const int64_t count = n * K;
    // (NC < L) the call's last sample stores its NC values alone, below.
    const int64_t whole = NC < L ? count - 1 : count;
    int64_t first = 0;
    if constexpr (NC == 3 && std::is_same_v<T, float>) {
      first = gather3_quads(xb, tl, f, down, count, cols);
    }
    if constexpr (weights_first<T, NC, CL>()) {
      alignas(64) float w[4 * WEIGHT_CHUNK];
      for (int64_t i0 = 0; i0 < count; i0 += WEIGHT_CHUNK) {
        const int64_t m = std::min(WEIGHT_CHUNK, count - i0);
        corner_weights(f + 2 * i0, m, w);
        for (int64_t j = 0; j < m; ++j) {
          const int64_t i = i0 + j;
          const T* a = xb + int64_t{tl[i]} * NC;
          for (int c0 = 0; c0 < L; c0 += CL) {
            const T* ac = a + c0;
            store(cols + i * NC + c0,
                  w[j] * load<V>(ac) + w[WEIGHT_CHUNK + j] * load<V>(ac + NC) +
                      w[2 * WEIGHT_CHUNK + j] * load<V>(ac + down) +
                      w[3 * WEIGHT_CHUNK + j] * load<V>(ac + down + NC));
          }
        }
      }
      return;
    }
    for (int64_t i = first; i < whole; ++i) {
      if constexpr (L == CL) {
        store(cols + i * NC, gather_sample<V, T, NC>(xb, tl, f, down, i, 0));
      } else {
        // Several chunks (16 to 64 channels): the weights once per sample. Written per chunk,
        // GCC recomputed them for every chunk (seen in the disassembly of the AVX-512
        // clone): against that, `calibconv bench` (one thread, Zen 4, 2 rounds) forward 32->16 at
        // 128x128 1.18-1.19 -> 1.02-1.04x conv2d, 64->32 at 64x64 1.26-1.32 -> 1.11-1.18x, 32->32
        // at 64x64 1.24 -> 1.11-1.13x; the same bits.
        const auto [w0, w1, w2, w3] = corners_at<T, NC>(f, i);
        const T* a = xb + int64_t{tl[i]} * NC;
        for (int c0 = 0; c0 < L; c0 += CL) {
          const T* ac = a + c0;
          store(cols + i * NC + c0, w0 * load<V>(ac) + w1 * load<V>(ac + NC) +
                                        w2 * load<V>(ac + down) + w3 * load<V>(ac + down + NC));
        }
      }
    }
    if (whole < count && count > 0) {  // NC = 3: one chunk
      const V v = gather_sample<V, T, NC>(xb, tl, f, down, whole, 0);
      for (int c = 0; c < NC; ++c) cols[whole * NC + c] = v[c];
    }
    return;
  }
  const int64_t row = K * C;
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = 0; k < K; ++k) {
      const Sample<T> sm = sample_at<T, NC>(xb, tl, f, t * K + k, C, down);
      T* dst = cols + t * row + k * Cg;
      if constexpr (NC > 0) {
        sample_channels(sm, 0, NC, dst);
      } else {
        for (int64_t gi = 0; gi < G; ++gi) sample_channels(sm, gi * Cg, Cg, dst + gi * K * Cg);
      }
    }
  }
}

// The columns [s0, s1) of the rows of output pixels [p0, p0 + n) of batch item b (one group),
// into cols [n, s1 - s0] at row stride ldc: for the few-output-channel kernels' large weights,
// whose forward gathers and multiplies a block's columns one slab at a time (forward_impl). Each
// value is gather_columns_body's expression (the same bits). coef: fractions (such layers have
// more than CORNER_WEIGHTS_MAX_C channels: a weight of SMALL_LARGE_WEIGHT values at 8 channels
// would need over 3000 outputs).
CALIBCONV_CLONES void gather_range_float(const Geo& g, const float* xp, const int32_t* top_left,
                                         const float* frac, int64_t b, int64_t p0, int64_t n,
                                         int64_t s0, int64_t s1, float* cols, int64_t ldc) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;  // per-item plans index the stacked padded items
  const int64_t C = g.C, K = g.K, down = g.Wp * C;
  const float* xb = xp + (b * frame - shift) * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const float* __restrict f = frac + 2 * s_begin;
  const int64_t k0 = s0 / C, k1 = (s1 + C - 1) / C;  // the taps the range covers
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = k0; k < k1; ++k) {
      const Sample<float> sm = sample_at<float, 0>(xb, tl, f, t * K + k, C, down);
      // (the channels [c0, c1) of tap k; channel c of the tap is column k * C + c)
      const int64_t c0 = std::max<int64_t>(s0 - k * C, 0), c1 = std::min<int64_t>(s1 - k * C, C);
      sample_channels(sm, c0, c1 - c0, cols + t * ldc + (k * C + c0 - s0));
    }
  }
}

// Adds the column-gradient tile gcols [n, K*C] (layout as the columns) of output pixels
// [p0, p0 + n) of batch item b to the corners they sampled, in the padded channels-last rows gxp
// (as padded_input; GradientRows holds them and writes them out). Corners off the input add into
// the padding; samples wholly outside (the plan's zero block) are skipped, so no two tasks of a
// phase write the same padding pixel. Every pixel of the input gets the same additions in the same
// order as in the scatter into the unpadded input that came before (which skipped out-of-range
// corners), the same bits (with Border::WrapX the first column's additions through the right
// padding column come last). In one C++ process against that scatter (float32, F195 plans, B8, one
// thread, the zeroing and the copy out included): 8 channels 0.75x at 64x64 and 0.87x at 128x128,
// 16 channels 0.84-0.87x.
// A corner of zero weight adds w * g = +-0, which leaves every value but -0 as it is, and no
// value here is -0 (the buffer starts at +0, and a sum is -0 only if both terms are): the same
// bits as skipping it, for every finite gradient (an infinite or NaN one spreads NaN to its
// zero-weight corners too). Such corners lie in the rows the plan's `rows` name (floor(y) and
// floor(y) + 1 of every sample), so the bands stay disjoint. The branch that skipped them cost
// more than the additions: two taken jumps a corner. Without it (F195 plans, one thread, Intel
// Xeon, calibrated / conv2d f+b, 2 processes each way alternating): 16->16 at 128x128 B8
// 1.51-1.53 -> 1.47-1.50x, 8->8 at 64x64 1.17-1.21 -> 1.09-1.12x, 16->16 at 64x64 1.42-1.46 ->
// 1.39-1.40x, 32->16 at 128x128 and 32-64 channels within the spread.
// NC as in gather_columns_body.
template <typename T, int NC, int CLW = chunk_lanes<T, NC>()>
CALIBCONV_ALWAYS_INLINE inline void scatter_columns_body(const Geo& g, T* gxp,
                                                         const int32_t* top_left, const T* coef,
                                                         int64_t b, int64_t p0, int64_t n,
                                                         const T* gcols) {
  const int64_t item = g.item(b);
  const int64_t frame = g.Hp * g.Wp;
  const int64_t shift = item * frame;
  const int64_t C = NC > 0 ? NC : g.C, Cg = NC > 0 ? NC : g.Cg, G = NC > 0 ? 1 : g.G;
  const int64_t K = g.K, down = g.Wp * C;
  const int64_t blank = shift + (g.H + 1) * g.Wp;
  T* gxb = gxp + (b * frame - shift) * C;
  const int64_t row = K * C;
  const int64_t s_begin = (item * g.P + p0) * K;
  const int32_t* __restrict tl = top_left + s_begin;
  const T* __restrict f = coef + coef_stride(NC) * s_begin;
  const int64_t corner[4] = {0, C, down, down + C};
  if constexpr (weights_first<T, NC, CLW>()) {  // one group: sample i's columns at i * NC
    using V = typename VecOf<T, CLW>::type;
    alignas(64) float w[4 * WEIGHT_CHUNK];
    const int64_t count = n * K;
    for (int64_t i0 = 0; i0 < count; i0 += WEIGHT_CHUNK) {
      const int64_t m = std::min(WEIGHT_CHUNK, count - i0);
      corner_weights(f + 2 * i0, m, w);
      for (int64_t j = 0; j < m; ++j) {
        const int64_t i = i0 + j;
        if (tl[i] == blank) continue;
        const T* __restrict src = gcols + i * NC;
        T* const a = gxb + int64_t{tl[i]} * C;
        for (int c = 0; c < 4; ++c) {
          T* __restrict dst = a + corner[c];
          const T wc = w[c * WEIGHT_CHUNK + j];
          for (int c0 = 0; c0 < NC; c0 += CLW) {
            store(dst + c0, load<V>(dst + c0) + wc * load<V>(src + c0));
          }
        }
      }
    }
    return;
  }
  for (int64_t t = 0; t < n; ++t) {
    for (int64_t k = 0; k < K; ++k) {
      const int64_t i = t * K + k;
      if (tl[i] == blank) continue;
      const Corners<T> cw = corners_at<T, NC>(f, i);
      const T w[4] = {cw.w0, cw.w1, cw.w2, cw.w3};
      const T* __restrict src = gcols + t * row + k * Cg;
      T* const a = gxb + int64_t{tl[i]} * C;
      for (int c = 0; c < 4; ++c) {
        T* __restrict dst = a + corner[c];
        const T wc = w[c];
        if constexpr (NC > 0 && VecOf<T, NC>::ok) {
          constexpr int CL = CLW;
          using V = typename VecOf<T, CL>::type;
          for (int c0 = 0; c0 < NC; c0 += CL) {
            store(dst + c0, load<V>(dst + c0) + wc * load<V>(src + c0));
          }
        } else if constexpr (NC > 0) {
          for (int j = 0; j < NC; ++j) dst[j] += wc * src[j];
        } else {
          for (int64_t gi = 0; gi < G; ++gi) {
            T* __restrict d = dst + gi * Cg;
            const T* __restrict q = src + gi * K * Cg;
            CALIBCONV_IVDEP
            for (int64_t j = 0; j < Cg; ++j) d[j] += wc * q[j];
          }
        }
      }
    }
  }
}

// The multiversioned entry points, one per (element type, fixed channel count): NC = 0 is the
// general case (any channels, any groups). CALIBCONV_TILE_KERNELS_AS names them
// gather_T_NC<SUFFIX> / scatter_T_NC<SUFFIX>, compiled with ATTR and chunks of CLW lanes
// (CALIBCONV_SCATTER_AS: the scatter alone).
#define CALIBCONV_SCATTER_AS(ATTR, T, NC, SUFFIX, CLW)                                          \
  ATTR void scatter_##T##_##NC##SUFFIX(const Geo& g, T* gxp, const int32_t* top_left,         \
                                       const T* coef, int64_t b, int64_t p0, int64_t n,        \
                                       const T* gcols) {                                       \
    scatter_columns_body<T, NC, CLW>(g, gxp, top_left, coef, b, p0, n, gcols);                 \
  }
#define CALIBCONV_TILE_KERNELS_AS(ATTR, T, NC, SUFFIX, CLW)                                     \
  ATTR void gather_##T##_##NC##SUFFIX(const Geo& g, const T* xp, const int32_t* top_left,     \
                                      const T* coef, int64_t b, int64_t p0, int64_t n,         \
                                      T* cols) {                                               \
    gather_columns_body<T, NC, CLW>(g, xp, top_left, coef, b, p0, n, cols);                    \
  }                                                                                            \
  CALIBCONV_SCATTER_AS(ATTR, T, NC, SUFFIX, CLW)
#define CALIBCONV_TILE_KERNELS(T, NC) \
  CALIBCONV_TILE_KERNELS_AS(CALIBCONV_CLONES, T, NC, , (chunk_lanes<T, NC>()))
#define CALIBCONV_TILE_KERNELS_ALL(T) \
  CALIBCONV_TILE_KERNELS(T, 0)        \
  CALIBCONV_TILE_KERNELS(T, 1)        \
  CALIBCONV_TILE_KERNELS(T, 2)        \
  CALIBCONV_TILE_KERNELS(T, 3)        \
  CALIBCONV_TILE_KERNELS(T, 4)        \
  CALIBCONV_TILE_KERNELS(T, 8)        \
  CALIBCONV_TILE_KERNELS(T, 16)       \
  CALIBCONV_TILE_KERNELS(T, 32)       \
  CALIBCONV_TILE_KERNELS(T, 64)
CALIBCONV_TILE_KERNELS_ALL(float)
CALIBCONV_TILE_KERNELS_ALL(double)

// The gather and scatter of 16, 32, 64, 128 and 256 float channels in whole 64-byte vectors, each
// chunk of samples' bilinear weights computed first (weights_first), compiled for AVX-512 only
// (x86-64-v4, as the few-output-channel kernels: in the multiversioned bodies above GCC would lower
// such vectors through the stack in the AVX2 clone) and picked where the CPU has it (tile_kernels).
// Each lane computes the same expression as the 32-byte chunks and the general loop (the same bits,
// which few_output_channel_kernels_agree_across_isa_levels checks). On an Intel Xeon (AVX-512 and
// AMX, one thread, two processes each way alternating, calibrated / conv2d forward and f+b): 32->16
// at 128x128 B8 1.37-1.40 / 1.60-1.66x -> 1.25-1.32 / 1.54-1.55x, 32->32 at 64x64 1.26 / 1.24-1.25x
// -> 1.20-1.22 / 1.19x, 64->32 at 64x64 1.37-1.40 / 1.40-1.41x -> 1.30-1.31 / 1.30-1.31x, 64->64 at
// 32x32 1.22 / 1.13-1.14x -> 1.16-1.18 / 1.09-1.10x. At 16 channels the scatter only: once it had
// no branches (see scatter_columns_body), 16->16 at 128x128 f+b 1.43-1.47 -> 1.38-1.39x, 16->16 at
// 64x64 1.36-1.42 -> 1.37x, 16->8 and 16->32 at 64x64 within the spread; the 64-byte gather of 16
// channels is no faster (16->8 at 64x64 forward 1.15-1.16 -> 1.19-1.20x, f+b 1.24-1.25 ->
// 1.24-1.27x; with the branchy scatter, 16->8 f+b 1.24-1.26 -> 1.29-1.30x); with the weights
// computed first (eighteenth session) it is: one thread, base -> this, 2 processes each
// alternating, 16->16 at 128x128 forward 1.33-1.34 -> 1.24-1.26x, f+b 1.33-1.34 -> 1.27-1.29x, at
// 64x64 forward 1.19-1.22 -> 1.09-1.10x; --presets forward goals holding 29-31 -> 33-35 of 38; 32
// channels and more within the spread (docs/bench/ eighteenth-session-ab.txt). 128 and 256 channels
// (sixteenth session; before, the general loop over a runtime channel count): 128->128 at 16x16 B8
// forward 1.14-1.33 -> 1.11-1.24x, f+b 1.21-1.24 -> 1.17-1.20x, 128->64 at 32x32 1.24 / 1.17-1.18x
// -> 1.20-1.21 / 1.11-1.12x, classic 128->128 at 128x128 B2 1.17 / 1.18-1.20x -> 1.14 / 1.16-1.17x.
// (The slabs of large weights, whole taps of 128-512 channels, through such a loop too: no change,
// at 256->128 on 16x16 1.25 -> 1.24x.) (On an AMD Zen 4, which splits 64-byte operations in two,
// the thirteenth session measured such chunks 4-5% faster as kernels and no change in a step.)
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 32, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 64, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 128, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 256, _v4, 16)
CALIBCONV_TILE_KERNELS_AS(CALIBCONV_TARGET_V4, float, 16, _v4, 16)
#endif

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

#define CALIBCONV_PICK_AS(T, NC, SUFFIX) \
  case NC:                               \
    return {gather_##T##_##NC##SUFFIX, scatter_##T##_##NC##SUFFIX, NC};
#define CALIBCONV_PICK(T, NC) CALIBCONV_PICK_AS(T, NC, )
#define CALIBCONV_PICK_ALL(T)                                 \
  switch (g.G == 1 ? g.C : 0) {                               \
    CALIBCONV_PICK(T, 1)                                      \
    CALIBCONV_PICK(T, 2)                                      \
    CALIBCONV_PICK(T, 3)                                      \
    CALIBCONV_PICK(T, 4)                                      \
    CALIBCONV_PICK(T, 8)                                      \
    CALIBCONV_PICK(T, 16)                                     \
    CALIBCONV_PICK(T, 32)                                     \
    CALIBCONV_PICK(T, 64)                                     \
    default:                                                  \
      return {gather_##T##_0, scatter_##T##_0, 0};            \
  }

template <typename T>
TileKernels<T> tile_kernels(const Geo& g);
template <>
TileKernels<float> tile_kernels<float>(const Geo& g) {
#ifdef CALIBCONV_HAVE_SMALL_KERNELS
  if (g.G == 1 && small_isa() == SmallIsa::Avx512) {
    switch (g.C) {
      CALIBCONV_PICK_AS(float, 32, _v4)
      CALIBCONV_PICK_AS(float, 64, _v4)
      CALIBCONV_PICK_AS(float, 128, _v4)
      CALIBCONV_PICK_AS(float, 256, _v4)
      CALIBCONV_PICK_AS(float, 16, _v4)
      default:
        break;
    }
  }
#endif
  CALIBCONV_PICK_ALL(float)
}
template <>
TileKernels<double> tile_kernels<double>(const Geo& g) {
  CALIBCONV_PICK_ALL(double)
}

// The columns of output pixels [p0, p0 + n) of every batch item from the padded batch input
// xq (padded_batch_input) into cols + b * ldb (item b's rows of K * 3 values, as
// gather_columns_body writes them): four items a vector of sixteen floats, each lane the same
// expression as gather_sample (the same bits). Each item's sample stores four values, the last
// on the next sample's first, which the call stores later; its last sample stores three.
template <int J>
CALIBCONV_ALWAYS_INLINE inline VecOf<float, 4>::type item_lanes(const VecOf<float, 16>::type& v) {
  return __builtin_shufflevector(v, v, 4 * J, 4 * J + 1, 4 * J + 2, 4 * J + 3);
}
CALIBCONV_CLONES void batch_gather(const Geo& g, const float* xq, const int32_t* top_left,
                                   const float* coef, int64_t p0, int64_t n, float* cols,
                                   int64_t ldb) {
  using V16 = VecOf<float, 16>::type;
  using V4 = VecOf<float, 4>::type;
  constexpr int NC = 3;
  const int64_t K = g.K, B = g.B, pix = batch_items(B) * 4, down = g.Wp * pix;
  const int32_t* __restrict tl = top_left + p0 * K;
  const float* __restrict f = coef + coef_stride(NC) * p0 * K;
  const int64_t count = n * K;
  for (int64_t i = 0; i < count; ++i) {
    const auto [w0, w1, w2, w3] = corners_at<float, NC>(f, i);
    const float* a = xq + int64_t{tl[i]} * pix;
    const bool last = i + 1 == count;
    for (int64_t b0 = 0; b0 < B; b0 += 4) {
      const float* ab = a + b0 * 4;
      const V16 v = w0 * load<V16>(ab) + w1 * load<V16>(ab + pix) + w2 * load<V16>(ab + down) +
                    w3 * load<V16>(ab + down + pix);
      const auto put = [&](int64_t b, const V4& u) CALIBCONV_ALWAYS_INLINE {
        float* d = cols + b * ldb + i * NC;
        if (!last) {
          store(d, u);
        } else {
          for (int c = 0; c < NC; ++c) d[c] = u[c];
        }
      };
      put(b0, item_lanes<0>(v));
      if (b0 + 1 < B) put(b0 + 1, item_lanes<1>(v));
      if (b0 + 2 < B) put(b0 + 2, item_lanes<2>(v));
      if (b0 + 3 < B) put(b0 + 3, item_lanes<3>(v));
    }
  }
}

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
enum class LargeWeights : int32_t { Auto = 0, Kernels = 1, Blas = 2 };
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

// Values of slack after the padded input: the gather's vector-of-four loads of 3 channels read
// one value past a pixel.
constexpr int64_t PAD_SLACK = 4;

// Row r of item b of the padded input (see padded_input) into d [Wp, C]: row r - 1 of the
// input from src (channels-last [B, H, W, C], or NCHW where `direct`), or zeros above and below
// it; then its padding columns.
template <typename T>
void pad_row(const Geo& g, const T* src, bool direct, int64_t b, int64_t r, T* d) {
  const int64_t C = g.C, H = g.H, W = g.W, Wp = g.Wp, y = r - 1;
  if (y < 0 || y >= H) {
    std::fill(d, d + Wp * C, T(0));
    return;
  }
  T* row = d + C;  // column 0
  if (direct) {  // NCHW: row y of every channel plane, interleaved
    const T* s = src + b * C * g.HW + y * W;
    // (the channel count fixed at compile time: the loop over a row's pixels unrolls)
    const auto interleave = [&](auto nc) {
      constexpr int64_t NC = decltype(nc)::value;
      for (int64_t x0 = 0; x0 < W; ++x0) {
        for (int64_t c = 0; c < NC; ++c) row[x0 * NC + c] = s[c * g.HW + x0];
      }
    };
    switch (C) {
      case 1: interleave(std::integral_constant<int64_t, 1>{}); break;
      case 2: interleave(std::integral_constant<int64_t, 2>{}); break;
      case 3: interleave(std::integral_constant<int64_t, 3>{}); break;
      default: interleave(std::integral_constant<int64_t, 4>{}); break;
    }
  } else {
    const T* s = src + (b * g.HW + y * W) * C;
    std::copy(s, s + W * C, row);
  }
  if (g.wrap) {
    std::copy(row + (W - 1) * C, row + W * C, d);
    std::copy(row, row + C, row + W * C);
  } else {
    std::fill(d, d + C, T(0));
    std::fill(row + W * C, row + (W + 1) * C, T(0));
  }
}

// Whether the padding (pad_row) reads the input as NCHW (an image of few channels, transposed in
// the same pass) rather than a channels-last copy.
bool pad_direct(const at::Tensor& input, const Geo& g) {
  return !input.is_contiguous(at::MemoryFormat::ChannelsLast) && g.C <= 4;
}

// The lowest and highest input row (-1 to H) that the output rows [oy0, oy1] of plan item `it`
// read (the plan's `rows`, [items, H_out, 2]); lo > hi where they read none.
std::pair<int64_t, int64_t> input_rows(const Geo& g, const int32_t* rows, int64_t it, int64_t oy0,
                                       int64_t oy1) {
  const int32_t* r = rows + it * g.Ho * 2;
  int64_t lo = INT64_MAX, hi = INT64_MIN;
  for (int64_t oy = oy0; oy <= oy1; ++oy) {
    if (r[2 * oy] > r[2 * oy + 1]) continue;
    lo = std::min<int64_t>(lo, r[2 * oy]);
    hi = std::max<int64_t>(hi, r[2 * oy + 1]);
  }
  return {lo, hi};
}

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

// gather_rows for the columns [s0, s1) (gather_range_float), into cols at row stride ldc.
void gather_range_rows(const Geo& g, PaddedRows<float>& src, const int32_t* top_left,
                       const float* coef, int64_t q0, int64_t n, int64_t s0, int64_t s1,
                       float* cols, int64_t ldc) {
  for_items(g.P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
    gather_range_float(g, src.piece(b, p0, len), top_left, coef, b, p0, len, s0, s1,
                       cols + off * ldc, ldc);
  });
}

// Few output channels with a large weight (blocks of SMALL_LARGE_BLOCK_ROWS rows): the forward
// and the weight gradient gather and multiply a block's columns one slab of SMALL_SLAB at a time,
// the slab in L2, instead of the block's whole rows at once (at 256 -> 256 on 8x8 maps B8, 2.3
// MiB a block, written out to L3 and read back slab by slab). Not with kept columns (a first
// layer's whole column matrix). width: the columns a gathered row holds.
struct ColumnSlabs {
  bool on;
  int64_t width;
};
ColumnSlabs column_slabs(const Geo& g, bool small, bool kept) {
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

// Layout conversions between NCHW and channels-last, blocked for the caches (ATen's strided
// copy for a permutation is several times slower) and parallel over batch items and pixels.

// Transposes the 8x8 block of floats with row i at src[i] into the rows dst[j] (each row its own
// pointer): three rounds of shuffles (pairs, quads, halves) on eight 8-float vectors, the register
// transpose of the AVX instruction set, written with GCC's generic shuffles so that every clone
// gets its own instructions.
CALIBCONV_ALWAYS_INLINE inline void transpose8x8_rows(const float* const (&src)[8],
                                                      float* const (&dst)[8]) {
#if defined(__GNUC__) && !defined(__clang__)
  using V = VecOf<float, 8>::type;
  typedef int32_t M __attribute__((vector_size(32)));
  V r[8], t[8], u[8];
  for (int i = 0; i < 8; ++i) r[i] = load<V>(src[i]);
  for (int i = 0; i < 8; i += 2) {
    t[i] = __builtin_shuffle(r[i], r[i + 1], M{0, 8, 1, 9, 4, 12, 5, 13});
    t[i + 1] = __builtin_shuffle(r[i], r[i + 1], M{2, 10, 3, 11, 6, 14, 7, 15});
  }
  for (int i = 0; i < 8; i += 4) {
    for (int h = 0; h < 2; ++h) {
      u[i + 2 * h] = __builtin_shuffle(t[i + h], t[i + h + 2], M{0, 1, 8, 9, 4, 5, 12, 13});
      u[i + 2 * h + 1] =
          __builtin_shuffle(t[i + h], t[i + h + 2], M{2, 3, 10, 11, 6, 7, 14, 15});
    }
  }
  for (int j = 0; j < 4; ++j) {
    store(dst[j], __builtin_shuffle(u[j], u[j + 4], M{0, 1, 2, 3, 8, 9, 10, 11}));
    store(dst[j + 4], __builtin_shuffle(u[j], u[j + 4], M{4, 5, 6, 7, 12, 13, 14, 15}));
  }
#else
  for (int i = 0; i < 8; ++i)
    for (int j = 0; j < 8; ++j) dst[j][i] = src[i][j];
#endif
}

// The same with row i at src + i * ss and row j at dst + j * ds.
CALIBCONV_ALWAYS_INLINE inline void transpose8x8(const float* __restrict src, int64_t ss,
                                                 float* __restrict dst, int64_t ds) {
  const float* const s[8] = {src,          src + ss,     src + 2 * ss, src + 3 * ss,
                             src + 4 * ss, src + 5 * ss, src + 6 * ss, src + 7 * ss};
  float* const d[8] = {dst,          dst + ds,     dst + 2 * ds, dst + 3 * ds,
                       dst + 4 * ds, dst + 5 * ds, dst + 6 * ds, dst + 7 * ds};
  transpose8x8_rows(s, d);
}

// convert_pixels for float: whole 8x8 blocks through transpose8x8 (copied element by element,
// the compiler left these loops scalar), the edges element by element.
CALIBCONV_CLONES void convert_pixels_float(const float* __restrict src, float* __restrict dst,
                                           int64_t C, int64_t HW, int64_t p0, int64_t n,
                                           bool to_cl) {
  constexpr int64_t PB = 64;
  const int64_t c8 = C / 8 * 8;
  for (int64_t q0 = p0; q0 < p0 + n; q0 += PB) {
    const int64_t q1 = std::min(p0 + n, q0 + PB), q8 = q0 + (q1 - q0) / 8 * 8;
    for (int64_t c0 = 0; c0 < c8; c0 += 8) {
      for (int64_t q = q0; q < q8; q += 8) {
        if (to_cl) {
          transpose8x8(src + c0 * HW + q, HW, dst + q * C + c0, C);
        } else {
          transpose8x8(src + q * C + c0, C, dst + c0 * HW + q, HW);
        }
      }
    }
    // The edges: the channels past the last multiple of 8 at every pixel, and every channel at
    // the pixels past the last multiple of 8.
    for (int64_t q = q0; q < q1; ++q) {
      for (int64_t c = q < q8 ? c8 : 0; c < C; ++c) {
        if (to_cl) {
          dst[q * C + c] = src[c * HW + q];
        } else {
          dst[c * HW + q] = src[q * C + c];
        }
      }
    }
  }
}

// One item: [C, HW] -> [HW, C] (to_cl) or back, for pixels [p0, p0 + n), in tiles of CB
// channels x PB pixels. CB = 8 strided rows at a time: rows H*W apart alias in the L1 cache when
// H*W is a power of two, and 8 fit its associativity. Float32 goes through
// convert_pixels_float (the same tiles, as register transposes).
template <typename T>
void convert_pixels(const T* __restrict src, T* __restrict dst, int64_t C, int64_t HW,
                    int64_t p0, int64_t n, bool to_cl) {
  if constexpr (std::is_same_v<T, float>) {
    return convert_pixels_float(src, dst, C, HW, p0, n, to_cl);
  }
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

template <typename T>
const T* rows_of(const T* y, bool cl, int64_t C, int64_t P, int64_t q0, int64_t n, T* buf) {
  if (cl) return y + q0 * C;
  for_items(P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
    convert_pixels(y + b * C * P, buf + (off - p0) * C, C, P, p0, len, true);
  });
  return buf;
}

template <typename T>
void write_rows(const T* src, T* dst, bool cl, int64_t C, int64_t P, int64_t q0, int64_t n) {
  if (cl) {
    std::memcpy(dst + q0 * C, src, n * C * sizeof(T));
    return;
  }
  for_items(P, q0, n, [&](int64_t b, int64_t p0, int64_t len, int64_t off) {
    convert_pixels(src + (off - p0) * C, dst + b * C * P, C, P, p0, len, false);
  });
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

// The weight packed as WP [G, C_out/G, K, C/G]: each output channel's [C/G, K] block
// transposed, through convert_pixels for a contiguous weight (8x8 register transposes for
// float; the scalar loop before them was 2.7% of a forward + backward's samples at 256 -> 256
// on 8x8 maps, 2.1% after), else by a strided copy.
at::Tensor pack_weight(const at::Tensor& weight, const Geo& g) {
  if (!weight.is_contiguous()) {
    return weight.reshape({g.G, g.Coutg, g.Cg, g.K}).transpose(2, 3).contiguous();
  }
  at::Tensor wp = at::empty({g.G, g.Coutg, g.K, g.Cg}, weight.options());
  AT_DISPATCH_FLOATING_TYPES(weight.scalar_type(), "calibconv_pack_weight", [&] {
    const scalar_t* w = weight.const_data_ptr<scalar_t>();
    scalar_t* d = wp.mutable_data_ptr<scalar_t>();
    const int64_t Cg = g.Cg, K = g.K;
    const int64_t grain = std::max<int64_t>(1, (1 << 15) / std::max<int64_t>(1, Cg * K));
    at::parallel_for(0, g.Cout, grain, [&](int64_t o0, int64_t o1) {
      for (int64_t o = o0; o < o1; ++o) {
        convert_pixels(w + o * Cg * K, d + o * K * Cg, Cg, K, 0, K, true);
      }
    });
  });
  return wp;
}

// The input as pad_row reads it: as it is (made contiguous) where `direct` (pad_direct), else
// channels-last.
template <typename T>
at::Tensor pad_source(const at::Tensor& input, bool direct) {
  return direct ? input.contiguous() : channels_last<T>(input);
}

// The input as the gather reads it: channels-last, padded to [B, H + 3, W + 2, C] (one row above,
// two below, one column on each side; see `padded_size` in plan.rs) with zeros, or with
// Border::WrapX the input's last column in the left padding column and its first in the right;
// then PAD_SLACK zeros. A copy of the input (a few percent of the gather's reads, which are
// 4 * K values a pixel); an NCHW input of few channels (an image) is transposed in the same pass.
// (The first layers of three channels read it; the other gathers pad one item at a time, as
// PaddedRows.)
template <typename T>
at::Tensor padded_input(const at::Tensor& input, const Geo& g) {
  const bool direct = pad_direct(input, g);
  const at::Tensor x = pad_source<T>(input, direct);
  const int64_t Wp = g.Wp, Hp = g.Hp, frame = Hp * Wp * g.C;
  at::Tensor out = at::empty({g.B * frame + PAD_SLACK}, x.options());
  const T* src = x.const_data_ptr<T>();
  T* dst = out.mutable_data_ptr<T>();
  std::fill(dst + g.B * frame, dst + g.B * frame + PAD_SLACK, T(0));
  const int64_t grain = std::max<int64_t>(1, (1 << 15) / std::max<int64_t>(1, Wp * g.C));
  at::parallel_for(0, g.B * Hp, grain, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) pad_row(g, src, direct, r / Hp, r % Hp, dst + r * Wp * g.C);
  });
  return out;
}


// One row of padded_batch_input: for x < W, o[x * pix + b * 4 + c] = row[b * sb + c * sc + x *
// sw] for the B items and c < 3, and 0 for c = 3. With sw = 1, four pixels of an item at a time:
// its three channels' four values are loaded as vectors and transposed into four pixels of
// [c0, c1, c2, 0], each one 16-byte store. (Before: a whole-row fill with zeros, then each
// item's channel copied at a stride of pix values, one scalar store a value: tiny's first layer,
// 3->8 at 64x64 B8, 61 -> 43 us a call at one thread, 44-46 -> 27 us at two; the same values.)
CALIBCONV_CLONES void pad_batch_row(const float* __restrict row, int64_t sb, int64_t sc, int64_t sw,
                                    int64_t B, int64_t W, int64_t pix, float* __restrict o) {
  typedef float v4 __attribute__((vector_size(16)));
  typedef int i4 __attribute__((vector_size(16)));
  for (int64_t b = 0; b < B; ++b) {
    const float* r = row + b * sb;
    float* ob = o + b * 4;
    int64_t x = 0;
    if (sw == 1) {
      const v4 z = {0.0f, 0.0f, 0.0f, 0.0f};
      for (; x + 4 <= W; x += 4) {
        const v4 a = load<v4>(r + x), c1 = load<v4>(r + sc + x), c2 = load<v4>(r + 2 * sc + x);
        const v4 t0 = __builtin_shuffle(a, c1, i4{0, 4, 1, 5});
        const v4 t1 = __builtin_shuffle(a, c1, i4{2, 6, 3, 7});
        const v4 t2 = __builtin_shuffle(c2, z, i4{0, 4, 1, 5});
        const v4 t3 = __builtin_shuffle(c2, z, i4{2, 6, 3, 7});
        store(ob + x * pix, __builtin_shuffle(t0, t2, i4{0, 1, 4, 5}));
        store(ob + (x + 1) * pix, __builtin_shuffle(t0, t2, i4{2, 3, 6, 7}));
        store(ob + (x + 2) * pix, __builtin_shuffle(t1, t3, i4{0, 1, 4, 5}));
        store(ob + (x + 3) * pix, __builtin_shuffle(t1, t3, i4{2, 3, 6, 7}));
      }
    }
    for (; x < W; ++x) {
      float* px = ob + x * pix;
      px[0] = r[x * sw];
      px[1] = r[sc + x * sw];
      px[2] = r[2 * sc + x * sw];
      px[3] = 0.0f;
    }
  }
}

// First layers gathered for the whole batch at once (batch_gather): float32, 3 channels, one
// plan for every item. The padded input then holds, per padded pixel, every item's channels side
// by side, four values an item (the fourth zero) and the items rounded up to a multiple of four
// (zeros): [H + 3, W + 2, B4, 4] as padded_input's frame (zeros around, or Border::WrapX's
// columns). A sample's corners are then whole vectors of four items (64 bytes), its bilinear
// weights computed once for the batch.
at::Tensor padded_batch_input(const at::Tensor& input, const Geo& g) {
  const int64_t H = g.H, W = g.W, Wp = g.Wp, Hp = g.Hp, pix = batch_items(g.B) * 4;
  at::Tensor out = at::empty({Hp * Wp * pix + PAD_SLACK}, input.options());
  const float* src = input.const_data_ptr<float>();
  float* dst = out.mutable_data_ptr<float>();
  const int64_t sb = input.stride(0), sc = input.stride(1), sh = input.stride(2),
                sw = input.stride(3);
  std::fill(dst + Hp * Wp * pix, dst + Hp * Wp * pix + PAD_SLACK, 0.0f);
  const int64_t items = g.B * 4;
  at::parallel_for(0, Hp, 1, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      float* d = dst + r * Wp * pix;
      const int64_t y = r - 1;
      if (y < 0 || y >= H) {
        std::fill(d, d + Wp * pix, 0.0f);
        continue;
      }
      pad_batch_row(src + y * sh, sb, sc, sw, g.B, W, pix, d + pix);
      if (items < pix) {  // the items that round B up to a multiple of four
        for (int64_t x = 1; x <= W; ++x) std::fill(d + x * pix + items, d + (x + 1) * pix, 0.0f);
      }
      std::fill(d, d + pix, 0.0f);  // the border columns
      std::fill(d + (W + 1) * pix, d + Wp * pix, 0.0f);
      if (g.wrap) {
        for (int64_t b = 0; b < g.B; ++b) {
          for (int64_t c = 0; c < 3; ++c) {
            const float* row = src + b * sb + c * sc + y * sh;
            d[b * 4 + c] = row[(W - 1) * sw];
            d[(W + 1) * pix + b * 4 + c] = row[0];
          }
        }
      }
    }
  });
  return out;
}

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

// The float32 weight [C_out, C, kh, kw] of one group as the few-output-channel kernels (float32
// only) multiply it: [K*C, C_out], rows in the columns' (tap, channel) order, stored as panels of
// P = small_panel(C_out) outputs ([C_out / P, K*C, P]), through weight_to_panels. One pass over
// the weight, not a strided copy of a permuted view (TensorIterator's took 5.9% of the forward
// pass at 64 -> 64 channels on 8x8 maps, a plain loop 4.2%).
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

// Pixels a task and a block of the passes of a whole batch at once (forward_batch,
// grad_weight_first): the rows of tile_rows and small_block_rows, shared by the items.
struct BatchTiles {
  int64_t per_task, block, tasks;
};
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

// The weight gradient of a three_channels first layer, [C_out, C, K]: tasks of output pixels as
// forward_batch, each accumulating, block by block and item by item within a block, into one
// accumulator per chunk of tasks (chunks fixed per thread count, as grad_weight_impl), the
// columns gathered again from xsrc: the padded batch input with one plan (batch_gather), else
// the padded input, item by item (per-item plans; the same values, so the same sums as with one
// plan holding those samples).
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

// forward_impl for three_channels layers with one plan for every item: tasks of output pixels,
// each for every item; per block of pixels the items' columns are gathered at once into the
// thread's buffer (item by item) and each item's block multiplied into its output rows.
// *padded: the padded batch input (a first layer's weight gradient gathers its columns again
// from it, grad_weight_first).
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

// The output in layout fmt; weight [C_out, C/G, kh, kw] as the caller has it.
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
  // then its transpose: at 64 channels on 8x8 maps the two copies took 7% of the forward pass).
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
  // Two threads, calibrated / conv2d f+b, 2 rounds alternating: 256->256 at 8x8 B8 1.20-1.22 ->
  // 1.09-1.13x, 256->128 at 16x16 1.13-1.16 -> 1.11x, classic 512->1024 at 16x16 B2 1.07-1.17 ->
  // 1.06x.
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
// as in one batch-sized padded buffer (the same bits). Before, that buffer (B * Hp * Wp * C
// values) was faulted in and zeroed row by row, and copied out once the scatter was done
// (unpadded_gradient): at 32 -> 16 channels on 128x128 maps B8 17 MiB, its page faults and the
// copy out of memory 3-4% of a forward + backward's perf samples.
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

// The coefficients that the kernels of layer g read from the plan's fractions frac [N * 2] (in
// the input's type): the fractions themselves, or where the kernels tile_kernels picks read
// corner weights (reads_corner_weights; batch_gather's 3 channels do not) those weights [N * 4],
// each sample's the same expression as where they are computed from fractions (corners_at).
at::Tensor sample_coefficients(const at::Tensor& frac, const Geo& g) {
  const int64_t nc = frac.scalar_type() == at::kFloat ? tile_kernels<float>(g).nc
                                                      : tile_kernels<double>(g).nc;
  if (!reads_corner_weights(nc)) return frac;
  const at::Tensor f = frac.contiguous();
  const int64_t n = f.numel() / 2;
  at::Tensor w = at::empty({n * 4}, f.options());
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "calibconv_corner_weights", [&] {
    const scalar_t* __restrict src = f.const_data_ptr<scalar_t>();
    scalar_t* __restrict dst = w.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, n, 4096, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const Corners<scalar_t> c = corners_at<scalar_t, 0>(src, i);  // (from fractions)
        dst[4 * i] = c.w0;
        dst[4 * i + 1] = c.w1;
        dst[4 * i + 2] = c.w2;
        dst[4 * i + 3] = c.w3;
      }
    });
  });
  return w;
}

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
    // sample) from forward to backward: 0.6 MiB for each 8-channel layer of the quick profile's
    // network, whose training step's peak memory went 25 -> 27 MiB with them kept.
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
