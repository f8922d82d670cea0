//! Building a [`SamplingPlan`]: torchvision's bilinear rule, one output row at a time, in
//! parallel over rows, written in place into the plan's tensors. The arithmetic is the geometry
//! crate's (`calibconv_geometry::plan`, shared with the Python package); this file owns the
//! tensors.

use calibconv_geometry::plan;
use tch::kind::Element;
use tch::{Device, Kind, Tensor};

use super::{Border, ConvGeometry, SamplingPlan};
use crate::error::{Error, Result};

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
    /// The geometry crate's description of this layout (the arithmetic lives there, see
    /// `calibconv_geometry::plan`).
    pub(super) fn plan_layout(&self) -> plan::PlanLayout {
        let ConvGeometry {
            kernel,
            stride,
            padding,
            dilation,
        } = self.geom;
        plan::PlanLayout {
            h: self.h,
            w: self.w,
            ho: self.ho,
            wo: self.wo,
            kernel,
            stride,
            padding,
            dilation,
            per_item: self.per_item,
            wrap: self.border == Border::WrapX,
        }
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
        // Indices are int32 (half the memory of int64); refuse what overflows (the ATen path's
        // corner indices as well).
        let layout = self.plan_layout();
        let Some(samples) = layout.samples(items) else {
            return Err(Error::InvalidArgument(format!(
                "a sampling plan of {items} x {ho}x{wo} x {taps} samples on a {h}x{w} input is \
                 too large for int32 indices"
            )));
        };
        let top_left = Tensor::empty([samples as i64], (Kind::Int, Device::Cpu));
        // SAFETY: `top_left` is a fresh contiguous int32 CPU tensor of `samples` elements, only
        // written through this slice (by disjoint row chunks) before it is moved into the plan.
        let tl = unsafe { elements_mut::<i32>(top_left.data_ptr(), samples) };
        calibconv_geometry::memory::advise_huge_pages(tl);
        let mut reach: Vec<[i32; 2]> = Vec::new();
        let frac = match kind {
            Kind::Float => filled::<f32>(2 * samples, |f| reach = layout.fill(off, tl, f)),
            _ => filled::<f64>(2 * samples, |f| reach = layout.fill(off, tl, f)),
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

#[cfg(test)]
pub(super) use calibconv_geometry::plan::floor;
