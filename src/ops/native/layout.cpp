// Layout conversions between NCHW and channels-last, blocked for the caches (ATen's strided copy
// for a permutation is several times slower) and parallel over batch items and pixels; the
// packed weight.

#include "deform.h"

#include <cstring>

namespace calibconv::native {

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

template const float* rows_of<float>(const float*, bool, int64_t, int64_t, int64_t, int64_t,
                                     float*);
template void write_rows<float>(const float*, float*, bool, int64_t, int64_t, int64_t, int64_t);
template const double* rows_of<double>(const double*, bool, int64_t, int64_t, int64_t, int64_t,
                                       double*);
template void write_rows<double>(const double*, double*, bool, int64_t, int64_t, int64_t,
                                 int64_t);

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

template at::Tensor channels_last<float>(const at::Tensor&);
template at::Tensor nchw<float>(const at::Tensor&);
template at::Tensor channels_last<double>(const at::Tensor&);
template at::Tensor nchw<double>(const at::Tensor&);

at::MemoryFormat memory_format(const at::Tensor& input) {
  return !input.is_contiguous() && input.is_contiguous(at::MemoryFormat::ChannelsLast)
             ? at::MemoryFormat::ChannelsLast
             : at::MemoryFormat::Contiguous;
}

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

template <typename T>
at::Tensor pad_source(const at::Tensor& input, bool direct) {
  return direct ? input.contiguous() : channels_last<T>(input);
}

template at::Tensor pad_source<float>(const at::Tensor&, bool);
template at::Tensor pad_source<double>(const at::Tensor&, bool);

}  // namespace calibconv::native
