// The padded input that the gathers read: one item's rows at a time (pad_row, for PaddedRows),
// the whole batch (padded_input), and the batch of a 3-channel first layer with its items side by
// side (padded_batch_input).

#include "gather.h"

#include <algorithm>
#include <climits>
#include <type_traits>

namespace calibconv::native {

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
template void pad_row<float>(const Geo&, const float*, bool, int64_t, int64_t, float*);
template void pad_row<double>(const Geo&, const double*, bool, int64_t, int64_t, double*);

bool pad_direct(const at::Tensor& input, const Geo& g) {
  return !input.is_contiguous(at::MemoryFormat::ChannelsLast) && g.C <= 4;
}

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
template at::Tensor padded_input<float>(const at::Tensor&, const Geo&);
template at::Tensor padded_input<double>(const at::Tensor&, const Geo&);

// One row of padded_batch_input: for x < W, o[x * pix + b * 4 + c] = row[b * sb + c * sc + x *
// sw] for the B items and c < 3, and 0 for c = 3. With sw = 1, four pixels of an item at a time:
// its three channels' four values are loaded as vectors and transposed into four pixels of
// [c0, c1, c2, 0], each one 16-byte store.
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

}  // namespace calibconv::native
