//! Building a [`SamplingPlan`]: torchvision's bilinear rule, one output row at a time, in
//! parallel over rows, written in place into the plan's tensors.

use rayon::prelude::*;
use tch::kind::Element;
use tch::{Device, Kind, Tensor};

use super::{padded_size, Border, ConvGeometry, SamplingPlan};
use crate::error::{Error, Result};

/// Plan weights: float32 or float64.
pub(super) trait PlanFloat: Element + Copy + Send + Sync {
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

/// A new contiguous CPU tensor of `n` elements of `T`, its memory filled by `fill`.
pub(super) fn filled<T: Element>(n: usize, fill: impl FnOnce(&mut [T])) -> Tensor {
    let t = Tensor::empty([n as i64], (T::KIND, Device::Cpu));
    // SAFETY: `t` is a fresh contiguous CPU tensor of exactly `n` elements of `T` (same size as
    // `T::KIND`, the contract of `Element`); nothing else refers to its memory while `fill` runs.
    let data = unsafe { elements_mut::<T>(t.data_ptr(), n) };
    calibconv_geometry::memory::advise_huge_pages(data);
    fill(data);
    t
}

/// The `n` elements of `T` at `data` (a tensor's `data_ptr`).
///
/// # Safety
/// `data` must be the memory of a live contiguous CPU tensor of `n` elements of kind `T::KIND`
/// that outlives the slice, and no other reference to that memory may be used while it lives.
unsafe fn elements_mut<'a, T: Element>(data: *mut std::ffi::c_void, n: usize) -> &'a mut [T] {
    if n == 0 {
        return &mut [];
    }
    std::slice::from_raw_parts_mut(data as *mut T, n)
}

/// The elements of a contiguous CPU tensor of kind `T::KIND`, read-only.
pub(super) fn elements<T: Element>(t: &Tensor) -> Result<&[T]> {
    if t.kind() != T::KIND || t.device() != Device::Cpu || !t.is_contiguous() {
        return Err(Error::InvalidArgument(format!(
            "internal: expected a contiguous CPU {:?} tensor, got {:?} on {:?}",
            T::KIND,
            t.kind(),
            t.device()
        )));
    }
    let n = t.numel();
    if n == 0 {
        return Ok(&[]);
    }
    // SAFETY: checked above: contiguous CPU memory of `n` elements of `T`, alive as long as `t`.
    Ok(unsafe { std::slice::from_raw_parts(t.data_ptr() as *const T, n) })
}

/// Everything [`SamplingPlan::new`] needs to place the samples of one output row.
pub(super) struct Layout {
    pub(super) h: i64,
    pub(super) w: i64,
    pub(super) ho: i64,
    pub(super) wo: i64,
    pub(super) geom: ConvGeometry,
    pub(super) per_item: bool,
    pub(super) border: Border,
}

impl Layout {
    /// Fills the corners and fractions of the `wo * K` samples of output row `row` (item-major:
    /// `row = item * H_out + oy`) from the offsets `off` (`[items, 2K, H_out, W_out]`); returns
    /// the lowest and highest input row of its in-range corners (`[i32::MAX, i32::MIN]` if none).
    ///
    /// torchvision's bilinear rule (a unit test holds every corner and fraction to the
    /// per-sample reference `tests::bilinear_border`), with the row's tap positions and offset
    /// rows looked up once, and the corners chosen without branches.
    pub(super) fn fill_row<O: Copy + Into<f64>, W: PlanFloat>(
        &self,
        off: &[O],
        row: usize,
        top_left: &mut [i32],
        frac: &mut [W],
    ) -> [i32; 2] {
        let (ho, wo, h, w) = (self.ho, self.wo, self.h, self.w);
        let ConvGeometry {
            kernel: [kh, kw],
            stride,
            padding,
            dilation,
        } = self.geom;
        let taps = (kh * kw) as usize;
        let (plane, wo_u) = ((ho * wo) as usize, wo as usize);
        let (item, oy) = (row as i64 / ho, row as i64 % ho);
        // Per-item plans stack the padded items: this item's first padded pixel, and its zero
        // block.
        let [hp, wp] = padded_size([h, w]);
        let padded_base = if self.per_item { item * hp * wp } else { 0 };
        let blank = (padded_base + (h + 1) * wp) as i32;
        let wrap = self.border == Border::WrapX;
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
            if std::arch::is_x86_feature_detected!("avx2") && !portable_fill_only() {
                // SAFETY: the CPU has AVX2, the only feature the function enables.
                return unsafe {
                    fill_row_zeros_avx2(&taps_of_row, args, padded_base, top_left, frac)
                };
            }
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

impl Layout {
    /// The plan for offsets `off` (`[items, 2K, H_out, W_out]`, `items = batch.unwrap_or(1)`).
    pub(super) fn build<O: Copy + Into<f64> + Sync>(
        &self,
        off: &[O],
        batch: Option<i64>,
        kind: Kind,
    ) -> Result<SamplingPlan> {
        if !matches!(kind, Kind::Float | Kind::Double) {
            return Err(Error::InvalidArgument(format!(
                "plan weights must be float32 or float64, got {kind:?}"
            )));
        }
        let (h, w, ho, wo) = (self.h, self.w, self.ho, self.wo);
        let taps = self.geom.kernel[0] * self.geom.kernel[1];
        let items = batch.unwrap_or(1);
        let samples = (items * ho * wo * taps) as usize;
        // Indices are int32 (half the memory of int64); refuse what overflows (the ATen path's
        // corner indices as well).
        let [hp, wp] = padded_size([h, w]);
        if items * hp * wp > i32::MAX as i64 || 4 * samples > i32::MAX as usize {
            return Err(Error::InvalidArgument(format!(
                "a sampling plan of {items} x {ho}x{wo} x {taps} samples on a {h}x{w} input is \
                 too large for int32 indices"
            )));
        }
        let row = (wo * taps) as usize;
        let top_left = Tensor::empty([samples as i64], (Kind::Int, Device::Cpu));
        // SAFETY: `top_left` is a fresh contiguous int32 CPU tensor of `samples` elements, only
        // written through this slice (by disjoint row chunks) before it is moved into the plan.
        let tl = unsafe { elements_mut::<i32>(top_left.data_ptr(), samples) };
        calibconv_geometry::memory::advise_huge_pages(tl);
        let mut reach: Vec<[i32; 2]> = Vec::new();
        fn rows_of<O: Copy + Into<f64> + Sync, W: PlanFloat>(
            layout: &Layout,
            off: &[O],
            tl: &mut [i32],
            frac: &mut [W],
            row: usize,
        ) -> Vec<[i32; 2]> {
            tl.par_chunks_mut(row)
                .zip(frac.par_chunks_mut(2 * row))
                .enumerate()
                .map(|(r, (t, f))| layout.fill_row(off, r, t, f))
                .collect()
        }
        let frac = match kind {
            Kind::Float => filled::<f32>(2 * samples, |f| reach = rows_of(self, off, tl, f, row)),
            _ => filled::<f64>(2 * samples, |f| reach = rows_of(self, off, tl, f, row)),
        };
        let rows: Vec<i32> = reach.into_iter().flatten().collect();
        Ok(SamplingPlan {
            index: None,
            top_left,
            frac,
            rows: Tensor::from_slice(&rows),
            input_size: [h, w],
            output_size: [ho, wo],
            kernel: self.geom.kernel,
            batch,
            border: self.border,
        })
    }
}
/// Whether this thread's tests asked for the portable [`fill_row_zeros`] (never outside tests):
/// the test of the fill holds both clones to the per-sample rule on a CPU with AVX2.
fn portable_fill_only() -> bool {
    #[cfg(test)]
    {
        super::tests::PORTABLE_FILL.with(|p| p.get())
    }
    #[cfg(not(test))]
    {
        false
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

/// [`Layout::fill_row`] with zeros outside (no wrap), a tap at a time so that the arithmetic
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
pub(super) fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}
