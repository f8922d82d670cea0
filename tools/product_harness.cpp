// The forward products of a calibrated layer alone: the few-output-channel kernels of
// src/ops/native/small_kernels.h run through the loops of forward.cpp's forward_impl (blocks of
// small_block_rows rows; for a large weight, slabs of SMALL_SLAB reduction steps in a buffer of
// that width; passes of small_panel(C_out) outputs inside the kernel), without the gather, the
// weight's packing or ATen. One slab buffer stands for every slab's columns and stays in the
// caches, as the gather leaves it in the layer. A change to the kernels or their blocking is then
// timed in seconds, not through a build of the crate and `calibconv bench`; what it gains there
// is an upper bound of what the layer gains (docs/bench/cpu-kernels.md). GCC only (the kernels are compiled per instruction set with GCC's target attributes).
//
//   g++ -O3 -std=c++17 -I src/ops/native tools/product_harness.cpp -o /tmp/product_harness
//   /tmp/product_harness time CIN COUT ROWS [BLOCK]
//       e.g. 1024 512 2048: classic's 1024->512 at 32x32, batch 2 (ROWS = B * H * W); prints
//       the medians of 7 runs of the whole layer's products (ms, GFLOP/s)
//   /tmp/product_harness check
//       a few shapes (small and large weights, rows that are no multiple of the kernels' R)
//       against a float64 reference; exit status 1 on a mismatch
//
// Exit status 3: this CPU has no few-output-channel kernels (neither AVX2 nor AVX-512).

#include "small_kernels.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

using namespace calibconv::native;

namespace {

struct Layer {
  int64_t cin, cout, rows, block;
  int64_t kc() const { return 9 * cin; }
  // The columns a slab buffer holds (as gather.h's column_slabs).
  int64_t width() const { return small_slab_width(kc(), cout); }
};

// y [rows, cout] = bias + columns [rows, kc] @ W^T, W [cout, kc] stored as panels wt (see
// small_panel): block by block, slab by slab, as forward_impl calls the kernel. fill(q0, m, s0,
// s1, cols) writes the columns [s0, s1) of rows [q0, q0 + m) into cols (row stride width), or
// does nothing (timing).
template <typename Fill>
void products(const SmallKernels& k, const Layer& l, const float* wt, const float* bias,
              float* cols, float* y, const Fill& fill) {
  const int64_t kc = l.kc(), width = l.width();
  for (int64_t q0 = 0; q0 < l.rows; q0 += l.block) {
    const int64_t m = std::min(l.block, l.rows - q0);
    for (int64_t s0 = 0; s0 < kc; s0 += width) {
      const int64_t s1 = std::min(kc, s0 + width);
      fill(q0, m, s0, s1, cols);
      k.forward(cols, m, width, kc, s0, s1, wt, bias, y + q0 * l.cout);
    }
  }
}

// W [cout, kc] as the kernels read it: cout / P panels [kc, P].
std::vector<float> panels(const std::vector<float>& w, int64_t cout, int64_t kc) {
  const int64_t P = small_panel(cout);
  std::vector<float> wt(w.size());
  for (int64_t o = 0; o < cout; ++o) {
    for (int64_t j = 0; j < kc; ++j) wt[(o / P) * kc * P + j * P + o % P] = w[o * kc + j];
  }
  return wt;
}

std::vector<float> random_values(size_t n, uint32_t seed) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> v(n);
  for (float& x : v) x = u(gen);
  return v;
}

SmallKernels kernels_or_exit(const Layer& l) {
  const SmallKernels k = small_kernels_for(l.cout, l.kc());
  if (!k) {
    std::fprintf(stderr, "no few-output-channel kernels for %ld->%ld on this CPU\n",
                 static_cast<long>(l.cin), static_cast<long>(l.cout));
    std::exit(small_isa() == SmallIsa::None ? 3 : 2);
  }
  return k;
}

// Every output against a float64 sum; the bound scales with the sum of the products' magnitudes.
bool check_one(Layer l) {
  const SmallKernels k = kernels_or_exit(l);
  const int64_t kc = l.kc(), width = l.width();
  const std::vector<float> a = random_values(l.rows * kc, 1);
  const std::vector<float> w = random_values(l.cout * kc, 2);
  const std::vector<float> bias = random_values(l.cout, 3);
  const std::vector<float> wt = panels(w, l.cout, kc);
  std::vector<float> cols(l.block * width), y(l.rows * l.cout, NAN);
  products(k, l, wt.data(), bias.data(), cols.data(), y.data(),
           [&](int64_t q0, int64_t m, int64_t s0, int64_t s1, float* c) {
             for (int64_t t = 0; t < m; ++t) {
               std::memcpy(c + t * width, &a[(q0 + t) * kc + s0], (s1 - s0) * sizeof(float));
             }
           });
  double worst = 0;
  for (int64_t t = 0; t < l.rows; ++t) {
    for (int64_t o = 0; o < l.cout; ++o) {
      double sum = bias[o], mag = std::fabs(bias[o]);
      for (int64_t j = 0; j < kc; ++j) {
        const double p = static_cast<double>(a[t * kc + j]) * w[o * kc + j];
        sum += p, mag += std::fabs(p);
      }
      const double err = std::fabs(y[t * l.cout + o] - sum) / (mag + 1e-30);
      worst = std::max(worst, std::isnan(err) ? INFINITY : err);
    }
  }
  const bool ok = worst < 1e-6;
  std::printf("%s %ld->%ld, %ld rows in blocks of %ld, slabs of %ld: worst error %.2e of the "
              "products' magnitude\n",
              ok ? "ok      " : "MISMATCH", static_cast<long>(l.cin), static_cast<long>(l.cout),
              static_cast<long>(l.rows), static_cast<long>(l.block), static_cast<long>(width),
              worst);
  return ok;
}

int check() {
  // (cin, cout, rows, block): whole reductions and slabs (128->512 and 256->1024 are large
  // weights: 1152 and 2304 steps in slabs of 512, the last one partial), blocks that leave rows
  // over (the kernels' 4-row and 1-row tails).
  const Layer layers[] = {{16, 8, 37, 24},   {16, 16, 29, 24},   {32, 32, 50, 24},
                          {64, 64, 50, 24},  {64, 128, 31, 24},  {32, 256, 29, 16},
                          {128, 512, 41, 32}, {256, 1024, 13, 8}};
  bool ok = true;
  for (const Layer& l : layers) ok = check_one(l) && ok;
  return ok ? 0 : 1;
}

int time_layer(Layer l) {
  const SmallKernels k = kernels_or_exit(l);
  if (l.block <= 0) l.block = small_block_rows(l.kc(), l.cout, l.rows);
  const int64_t kc = l.kc(), width = l.width();
  const std::vector<float> wt = random_values(l.cout * kc, 2);
  const std::vector<float> bias = random_values(l.cout, 3);
  std::vector<float> cols = random_values(l.block * width, 1), y(l.rows * l.cout);
  const auto none = [](int64_t, int64_t, int64_t, int64_t, float*) {};
  products(k, l, wt.data(), bias.data(), cols.data(), y.data(), none);  // warm up
  std::vector<double> ms;
  for (int r = 0; r < 7; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    products(k, l, wt.data(), bias.data(), cols.data(), y.data(), none);
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0)
                     .count());
  }
  std::sort(ms.begin(), ms.end());
  const double flop = 2.0 * l.rows * kc * l.cout;
  std::printf("%ld->%ld, %ld rows in blocks of %ld, slabs of %ld: %.2f ms (median of 7; %.2f to "
              "%.2f), %.1f GFLOP/s\n",
              static_cast<long>(l.cin), static_cast<long>(l.cout), static_cast<long>(l.rows),
              static_cast<long>(l.block), static_cast<long>(width), ms[3], ms[0], ms[6],
              flop / ms[3] / 1e6);
  return 0;
}

int usage() {
  std::fprintf(stderr, "usage: product_harness time CIN COUT ROWS [BLOCK] | check\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc == 2 && std::string(argv[1]) == "check") return check();
  if ((argc == 5 || argc == 6) && std::string(argv[1]) == "time") {
    const Layer l{std::atol(argv[2]), std::atol(argv[3]), std::atol(argv[4]),
                  argc == 6 ? std::atol(argv[5]) : 0};
    if (l.cin <= 0 || l.cout <= 0 || l.rows <= 0) return usage();
    return time_layer(l);
  }
  return usage();
}
