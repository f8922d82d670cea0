//! The sampling plan's arithmetic over plain slices: for every (output pixel, tap) of a
//! deformable convolution with fixed offsets, the top-left bilinear corner in the padded input
//! and the fractional parts of the sample position, with torchvision's bilinear rule.
//!
//! One implementation for both users: `calibconv::ops` wraps it in tensors (`SamplingPlan`, whose
//! docs give the design), and the Python package's binding returns it as numpy arrays for the
//! same native kernels compiled as a torch extension.
//!
//! # Layout
//! Samples are pixel-major (`P = H_out * W_out` output pixels, `K = kh * kw` taps, tap-minor),
//! items stacked for per-item offsets. `top_left[s]` indexes the input *padded* by one row above,
//! two below and one column on each side ([`padded_size`], per-item plans: item `b`'s indices
//! offset by `b * (H + 3) * (W + 2)`); `frac[2 s..2 s + 2]` holds `(ly, lx)`. A sample wholly
//! outside (`y <= -1`, `y >= H`, `x <= -1`, `x >= W`, or non-finite) points at the item's zero
//! block (row `H + 1` of the padded frame, its first column) with fractions 0; with `wrap` columns
//! are periodic (any finite `x` samples the input). Per output row (item-major), the lowest and
//! highest input row its in-range corners read (`[i32::MAX, i32::MIN]` if none): the native input
//! gradient's schedule. Conventions: pixel centres at integers, positions `(y, x)` = (row,
//! column).

use rayon::prelude::*;

/// Plan fractions: float32 or float64 (rounded from the float64 arithmetic).
pub trait PlanFloat: Copy + Send + Sync {
    fn from_f64(v: f64) -> Self;
}
impl PlanFloat for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}
impl PlanFloat for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
}

/// Which clone of the fill without wrap [`PlanLayout::fill_row`] runs (the values are the same).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FillPath {
    /// AVX2 where the CPU has it, else portable.
    Fastest,
    /// The portable clone even where AVX2 is there (for the tests that hold both clones to the
    /// reference).
    Portable,
}

/// `[H + 3, W + 2]`: the size of an `[H, W]` input padded as the plan's `top_left` indices read
/// it (one row above and two below, one column on each side).
pub fn padded_size([h, w]: [i64; 2]) -> [i64; 2] {
    [h + 3, w + 2]
}

/// Everything needed to place the samples of one output row: the input `h x w`, the output
/// `ho x wo`, the convolution's kernel, stride, padding and dilation (each `[rows, columns]`,
/// PyTorch's conventions), per-item offsets, and the border rule (`wrap`: columns modulo `w`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlanLayout {
    pub h: i64,
    pub w: i64,
    pub ho: i64,
    pub wo: i64,
    pub kernel: [i64; 2],
    pub stride: [i64; 2],
    pub padding: [i64; 2],
    pub dilation: [i64; 2],
    pub per_item: bool,
    pub wrap: bool,
}

impl PlanLayout {
    /// Samples of `items` plan items (`items * H_out * W_out * K`), or `None` where the plan's
    /// int32 indices would overflow (its top-left corners, and the four corner indices per
    /// sample of `calibconv`'s ATen path).
    pub fn samples(&self, items: i64) -> Option<usize> {
        let taps = self.kernel[0] * self.kernel[1];
        let samples = items * self.ho * self.wo * taps;
        let [hp, wp] = padded_size([self.h, self.w]);
        (items * hp * wp <= i32::MAX as i64 && 4 * samples <= i32::MAX as i64)
            .then_some(samples as usize)
    }

    /// Fills the whole plan for offsets `off` (`[items, 2K, H_out, W_out]`, torchvision's layout:
    /// per tap, row-major, `(dy, dx)`) into `top_left` (`[samples]`) and `frac`
    /// (`[2 * samples]`), in parallel over output rows; returns each row's input rows (see the
    /// module docs). The caller sizes the slices with [`PlanLayout::samples`].
    pub fn fill<O: Copy + Into<f64> + Sync, W: PlanFloat>(
        &self,
        off: &[O],
        top_left: &mut [i32],
        frac: &mut [W],
    ) -> Vec<[i32; 2]> {
        let row = (self.wo * self.kernel[0] * self.kernel[1]) as usize;
        top_left
            .par_chunks_mut(row)
            .zip(frac.par_chunks_mut(2 * row))
            .enumerate()
            .map(|(r, (t, f))| self.fill_row(off, r, t, f, FillPath::Fastest))
            .collect()
    }

    /// Fills the corners and fractions of the `wo * K` samples of output row `row` (item-major:
    /// `row = item * H_out + oy`) from the offsets `off` (`[items, 2K, H_out, W_out]`); returns
    /// the lowest and highest input row of its in-range corners (`[i32::MAX, i32::MIN]` if none).
    ///
    /// torchvision's bilinear rule (`calibconv`'s plan tests hold every corner and fraction to a
    /// per-sample reference), with the row's tap positions and offset rows looked up once, and
    /// the corners chosen without branches (AVX2 where the CPU has it and `path` allows it).
    pub fn fill_row<O: Copy + Into<f64>, W: PlanFloat>(
        &self,
        off: &[O],
        row: usize,
        top_left: &mut [i32],
        frac: &mut [W],
        path: FillPath,
    ) -> [i32; 2] {
        let (ho, wo, h, w) = (self.ho, self.wo, self.h, self.w);
        let PlanLayout {
            kernel: [kh, kw],
            stride,
            padding,
            dilation,
            ..
        } = *self;
        let taps = (kh * kw) as usize;
        let (plane, wo_u) = ((ho * wo) as usize, wo as usize);
        let (item, oy) = (row as i64 / ho, row as i64 % ho);
        // Per-item plans stack the padded items: this item's first padded pixel, and its zero
        // block.
        let [hp, wp] = padded_size([h, w]);
        let padded_base = if self.per_item { item * hp * wp } else { 0 };
        let blank = (padded_base + (h + 1) * wp) as i32;
        let wrap = self.wrap;
        let (hf, wf) = (h as f64, w as f64);
        // Per tap: its regular position (row; column at ox = 0) and its offset rows.
        let item_off = &off[item as usize * 2 * taps * plane..];
        let start = oy as usize * wo_u;
        let tap = |k: usize| {
            let (i, j) = (k as i64 / kw, k as i64 % kw);
            let dy = &item_off[2 * k * plane + start..][..wo_u];
            let dx = &item_off[(2 * k + 1) * plane + start..][..wo_u];
            let y = (oy * stride[0] - padding[0] + i * dilation[0]) as f64;
            (y, j * dilation[1] - padding[1], dy, dx)
        };
        let taps_of_row: Vec<_> = (0..taps).map(tap).collect();
        let (top_left, frac) = (&mut top_left[..taps * wo_u], &mut frac[..2 * taps * wo_u]);
        if !wrap {
            let args = [stride[1], h, w];
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") && path == FillPath::Fastest {
                // SAFETY: the CPU has AVX2, the only feature the function enables.
                return unsafe {
                    fill_row_zeros_avx2(&taps_of_row, args, padded_base, top_left, frac)
                };
            }
            let _ = path;
            return fill_row_zeros(&taps_of_row, args, padded_base, top_left, frac);
        }
        let mut reach = [i32::MAX, i32::MIN];
        for (ox, (fracs, tls)) in frac
            .chunks_exact_mut(2 * taps)
            .zip(top_left.chunks_exact_mut(taps))
            .enumerate()
        {
            let ox_in = ox as i64 * stride[1];
            for (k, &(ty, tx, dy, dx)) in taps_of_row.iter().enumerate() {
                let y = ty + dy[ox].into();
                let x = (ox_in + tx) as f64 + dx[ox].into();
                // `!(a < b)` rather than `a >= b`: NaN lands outside as well.
                let outside =
                    !(y > -1.0 && y < hf && x.is_finite() && (wrap || (x > -1.0 && x < wf)));
                let f = &mut fracs[2 * k..2 * k + 2];
                if outside {
                    f.fill(W::from_f64(0.0));
                    tls[k] = blank;
                    continue;
                }
                let (fy, fx) = (floor(y), floor(x));
                // Wrapped: the top-left corner's column modulo w (its right neighbour, column
                // w, is the padding column that holds column 0).
                let (y0, x0) = (fy as i64, (fx as i64).rem_euclid(w));
                tls[k] = (padded_base + (y0 + 1) * wp + x0 + 1) as i32;
                // Corner rows are floor(y) and floor(y) + 1 (a superset is safe).
                reach = [reach[0].min(y0 as i32), reach[1].max(y0 as i32 + 1)];
                f[0] = W::from_f64(y - fy);
                f[1] = W::from_f64(x - fx);
            }
        }
        reach
    }
}

/// [`fill_row_zeros`] compiled for AVX2 (4 samples a step instead of 2).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fill_row_zeros_avx2<O: Copy + Into<f64>, W: PlanFloat>(
    taps_of_row: &[(f64, i64, &[O], &[O])],
    geometry: [i64; 3],
    padded_base: i64,
    top_left: &mut [i32],
    frac: &mut [W],
) -> [i32; 2] {
    fill_row_zeros(taps_of_row, geometry, padded_base, top_left, frac)
}

/// [`PlanLayout::fill_row`] with zeros outside (no wrap), a tap at a time so that the arithmetic
/// vectorises: per tap, the row's samples are computed into columns (top-left corners,
/// fractions) by a loop without branches or bounds checks, then stored to their places in the
/// plan. The same values as the per-sample rule: a sample inside (`-1 < y < h`, `-1 < x < w`)
/// has its top-left corner at `(floor(y), floor(x))` of the padded input and fractions
/// `y - floor(y)`, `x - floor(x)`; outside, it points at the zero block and the fractions are 0.
/// `taps_of_row[k] = (y of tap k, its column offset at ox = 0, dy row, dx row)`; `padded_base`:
/// the item's first index in the stacked padded input.
#[inline(always)]
fn fill_row_zeros<O: Copy + Into<f64>, W: PlanFloat>(
    taps_of_row: &[(f64, i64, &[O], &[O])],
    [stride_x, h, w]: [i64; 3],
    padded_base: i64,
    top_left: &mut [i32],
    frac: &mut [W],
) -> [i32; 2] {
    let taps = taps_of_row.len();
    let wo = top_left.len() / taps;
    let (hf, wf) = (h as f64, w as f64);
    // Indices wrap in i32: an index that is stored is a real one (< 2^31, checked when the plan
    // is sized), and modular arithmetic gets it right whatever the intermediate values.
    let wp32 = padded_size([h, w])[1] as i32;
    // The padded input's first pixel of row 0 of this item (top-left corners add y0 * wp + x0),
    // and its zero block (row h, column -1) for samples outside.
    let padded_origin = (padded_base as i32).wrapping_add(wp32).wrapping_add(1);
    let blank = (padded_base as i32).wrapping_add((h as i32 + 1).wrapping_mul(wp32));
    let column: Vec<f64> = (0..wo as i64).map(|ox| (ox * stride_x) as f64).collect();
    let (mut fy_col, mut fx_col) = (vec![W::from_f64(0.0); wo], vec![W::from_f64(0.0); wo]);
    let mut tl_col = vec![0i32; wo];
    let (mut lo, mut hi) = (i32::MAX, i32::MIN);
    for (k, &(ty, tx, dy, dx)) in taps_of_row.iter().enumerate() {
        let (dy, dx, column) = (&dy[..wo], &dx[..wo], &column[..wo]);
        let tl_c = &mut tl_col[..wo];
        let (fy_c, fx_c) = (&mut fy_col[..wo], &mut fx_col[..wo]);
        let txf = tx as f64;
        for ox in 0..wo {
            let y = ty + dy[ox].into();
            let x = (column[ox] + txf) + dx[ox].into();
            // `a > b` is false for NaN: non-finite samples land outside.
            let inside = y > -1.0 && y < hf && x > -1.0 && x < wf;
            // Outside samples are computed at (0, 0), then replaced: the i32 floors below only
            // see values in (-1, max(h, w)).
            let (fy, fx) = (
                floor32(if inside { y } else { 0.0 }),
                floor32(if inside { x } else { 0.0 }),
            );
            let (y0, x0) = (fy as i32, fx as i32);
            let padded = padded_origin
                .wrapping_add(y0.wrapping_mul(wp32))
                .wrapping_add(x0);
            tl_c[ox] = if inside { padded } else { blank };
            fy_c[ox] = W::from_f64(if inside { y - fy } else { 0.0 });
            fx_c[ox] = W::from_f64(if inside { x - fx } else { 0.0 });
            // Corner rows are floor(y) and floor(y) + 1 (a superset is safe).
            lo = lo.min(if inside { y0 } else { i32::MAX });
            hi = hi.max(if inside { y0 + 1 } else { i32::MIN });
        }
        for ox in 0..wo {
            let s = ox * taps + k;
            top_left[s] = tl_col[ox];
            frac[2 * s] = fy_c[ox];
            frac[2 * s + 1] = fx_c[ox];
        }
    }
    [lo, hi]
}

/// [`floor`] for finite `|v| < 2^31` (through i32, which vectorises).
#[inline(always)]
fn floor32(v: f64) -> f64 {
    let t = v as i32 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

/// `v.floor()` for finite `|v| < 2^53`, inline (without SSE4.1, `f64::floor` is a libm call that
/// costs a tenth of the plan build).
#[inline]
pub fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}
