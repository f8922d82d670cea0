//! The sampling plan: bilinear corner indices and weights of every (output pixel, tap).

use rayon::prelude::*;
use tch::kind::Element;
use tch::{Device, Kind, Tensor};

use super::check_float;
use crate::error::{Error, Result};
use crate::kernel::Offsets;

/// What a bilinear sample reads outside the input.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Border {
    /// torchvision's rule: corners outside the input read zero.
    #[default]
    Zeros,
    /// Columns are periodic (a 360-degree panorama): a corner's column is taken modulo `W`, so
    /// any finite `x` samples the input; rows outside still read zero.
    WrapX,
}

/// A convolution's geometry besides its input: kernel size, stride, padding and dilation, each
/// `[rows, columns]` (PyTorch's conventions).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ConvGeometry {
    pub kernel: [i64; 2],
    pub stride: [i64; 2],
    pub padding: [i64; 2],
    pub dilation: [i64; 2],
}

impl ConvGeometry {
    pub fn new(kernel: [i64; 2], stride: [i64; 2], padding: [i64; 2], dilation: [i64; 2]) -> Self {
        ConvGeometry {
            kernel,
            stride,
            padding,
            dilation,
        }
    }

    /// The geometry of a layer with `offsets` (their kernel size) and the given spacing.
    pub fn for_offsets(
        offsets: &Offsets,
        stride: [i64; 2],
        padding: [i64; 2],
        dilation: [i64; 2],
    ) -> Self {
        Self::new(offsets.kernel.map(|v| v as i64), stride, padding, dilation)
    }

    /// Output size `[H_out, W_out]` on an `input_size = [H, W]` input (PyTorch's formula), or an
    /// error naming the geometry if it is invalid or does not fit.
    pub fn output_size(&self, input_size: [i64; 2]) -> Result<[i64; 2]> {
        let ConvGeometry {
            kernel,
            stride,
            padding,
            dilation,
        } = *self;
        let [h, w] = input_size;
        if kernel.iter().chain(&input_size).any(|&v| v < 1)
            || stride.iter().chain(&dilation).any(|&v| v < 1)
            || padding.iter().any(|&p| p < 0)
        {
            return Err(Error::InvalidArgument(format!(
                "input {input_size:?}, kernel {kernel:?}, stride {stride:?}, padding {padding:?}, \
                 dilation {dilation:?}: sizes, strides and dilations must be >= 1, padding >= 0"
            )));
        }
        let dim = |a: usize| {
            (input_size[a] + 2 * padding[a] - dilation[a] * (kernel[a] - 1) - 1) / stride[a] + 1
        };
        let (ho, wo) = (dim(0), dim(1));
        if ho < 1 || wo < 1 {
            return Err(Error::InvalidArgument(format!(
                "kernel {kernel:?} with padding {padding:?}, dilation {dilation:?} does not fit a \
                 {h}x{w} input"
            )));
        }
        Ok([ho, wo])
    }
}

/// Precomputed bilinear sampling of a deformable convolution with fixed offsets.
///
/// For `N = P * K` samples (`P = H_out*W_out` output pixels, `K = kh*kw` taps, pixel-major;
/// times `B` for per-item offsets), `top_left` `[N]` (int32, CPU) holds the index of each
/// sample's top-left bilinear corner in the input *padded* by one row above, two below and one
/// column on each side (`(H + 3) x (W + 2)` pixels, [`padded_size`]; per-item plans index the
/// stacked padded items, item `b`'s indices offset by `b * (H + 3) * (W + 2)`), and `frac`
/// `[N * 2]` the fractional parts `(ly, lx)` of the sample position, from which the corner
/// weights follow: `(1-ly)(1-lx), (1-ly)lx, ly(1-lx), ly lx` ([`SamplingPlan::f_weights`]);
/// 12 bytes a float32 sample. In the padded input a sample's four corners (top-left, top-right,
/// bottom-left, bottom-right) are always `t, t + 1, t + W + 2, t + W + 3`: a sample inside
/// (`-1 < y < H`, `-1 < x < W`; torchvision's rule) has its top-left corner in rows `-1..H` and
/// columns `-1..W`, so corners off the input read the padding's zeros, and a sample outside
/// points at the block of rows `H..H+2`, columns `-1..1`, all zeros (fractions 0). With
/// [`Border::WrapX`] the top-left corner's column is taken modulo `W` and the right padding
/// column holds the input's first column (the native kernels fill it so). Every border rule
/// only moves corners, so the weights are the same for all of them. The native CPU kernels read
/// this form: one index a sample, no selects for corners off the input (against four corner
/// indices with a select each, the gather of 3-16 channels took 0.6-0.8x the time).
///
/// The ATen path (any device) computes a column as one weighted "bag" of four rows of a
/// pixel-major table with libtorch's `embedding_bag`, which computes (and differentiates) it in
/// one fused op: its indices ([`SamplingPlan::corner_index`]) point into the input's `H*W`
/// pixels, with one extra zero row at index `H*W` for corners outside the input, items stacked
/// each with its zero row. A CPU plan derives them when asked; a plan moved to another device
/// keeps them (16 more bytes a sample there). `rows` `[items, H_out, 2]` (int32) holds, per
/// output row, the lowest and highest input row its in-range corners read (lowest > highest if
/// none): the native input gradient schedules its scatter with it.
#[derive(Debug)]
pub struct SamplingPlan {
    /// `[N * 4]` int32: four corners per sample, kept on devices other than the CPU only (see
    /// [`SamplingPlan::corner_index`]).
    index: Option<Tensor>,
    /// `[N]` int32 (CPU): each sample's top-left corner in the padded input.
    top_left: Tensor,
    /// `[N * 2]`: `(ly, lx)` per sample, in the plan's kind.
    frac: Tensor,
    /// `[items, H_out, 2]` int32: input rows read by each output row.
    rows: Tensor,
    input_size: [i64; 2],
    output_size: [i64; 2],
    kernel: [i64; 2],
    /// `Some(B)` for per-item offsets.
    batch: Option<i64>,
    border: Border,
}

/// `[H + 3, W + 2]`: the size of an `[H, W]` input padded as the plan's `top_left` indices read
/// it (one row above and two below, one column on each side).
pub fn padded_size([h, w]: [i64; 2]) -> [i64; 2] {
    [h + 3, w + 2]
}

/// Plan weights: float32 or float64.
trait PlanFloat: Element + Copy + Send + Sync {
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
fn filled<T: Element>(n: usize, fill: impl FnOnce(&mut [T])) -> Tensor {
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
fn elements<T: Element>(t: &Tensor) -> Result<&[T]> {
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
struct Layout {
    h: i64,
    w: i64,
    ho: i64,
    wo: i64,
    geom: ConvGeometry,
    per_item: bool,
    border: Border,
}

impl Layout {
    /// Fills the corners and fractions of the `wo * K` samples of output row `row` (item-major:
    /// `row = item * H_out + oy`) from the offsets `off` (`[items, 2K, H_out, W_out]`); returns
    /// the lowest and highest input row of its in-range corners (`[i32::MAX, i32::MIN]` if none).
    ///
    /// torchvision's bilinear rule (a unit test holds every corner and fraction to the
    /// per-sample reference `tests::bilinear_border`), with the row's tap positions and offset
    /// rows looked up once, and the corners chosen without branches.
    fn fill_row<O: Copy + Into<f64>, W: PlanFloat>(
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
    fn build<O: Copy + Into<f64> + Sync>(
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

impl SamplingPlan {
    /// Builds the plan from offsets `[2*kh*kw, H_out, W_out]` or `[B, 2*kh*kw, H_out, W_out]`
    /// for an input of `input_size = [H, W]`; weights are stored in `kind` (float32 or
    /// float64), tensors on the CPU. Runs in parallel over output rows. Zeros outside the input
    /// (torchvision); see [`SamplingPlan::with_border`].
    pub fn new(
        offsets: &Tensor,
        input_size: [i64; 2],
        geom: ConvGeometry,
        kind: Kind,
    ) -> Result<Self> {
        Self::with_border(offsets, input_size, geom, kind, Border::Zeros)
    }

    /// [`SamplingPlan::new`] with a choice of what is read outside the input: with
    /// [`Border::WrapX`] the convolution's horizontal zero padding reads the other side of the
    /// image as well (circular padding in x).
    pub fn with_border(
        offsets: &Tensor,
        input_size: [i64; 2],
        geom: ConvGeometry,
        kind: Kind,
        border: Border,
    ) -> Result<Self> {
        check_float(offsets, "offsets")?;
        let [ho, wo] = geom.output_size(input_size)?;
        let kernel = geom.kernel;
        let taps = kernel[0] * kernel[1];
        let batch = match offsets.size().as_slice() {
            [c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] => None,
            [b, c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] && *b >= 1 => Some(*b),
            other => {
                return Err(Error::InvalidArgument(format!(
                    "offsets must be [{}, {ho}, {wo}] or [B, {}, {ho}, {wo}] for a {}x{} \
                     kernel on a {}x{} input, got {other:?}",
                    2 * taps,
                    2 * taps,
                    kernel[0],
                    kernel[1],
                    input_size[0],
                    input_size[1]
                )))
            }
        };
        let layout = Layout {
            h: input_size[0],
            w: input_size[1],
            ho,
            wo,
            geom,
            per_item: batch.is_some(),
            border,
        };
        let off = offsets.to_device(Device::Cpu).contiguous();
        match off.kind() {
            Kind::Float => layout.build(elements::<f32>(&off)?, batch, kind),
            _ => layout.build(elements::<f64>(&off)?, batch, kind),
        }
    }

    /// [`SamplingPlan::with_border`] straight from a layer's [`Offsets`] (shared by the batch),
    /// without copying them into a tensor first; `geom.kernel` must be the offsets' kernel
    /// ([`ConvGeometry::for_offsets`]).
    pub fn from_offsets(
        offsets: &Offsets,
        geom: ConvGeometry,
        kind: Kind,
        border: Border,
    ) -> Result<Self> {
        let input_size = offsets.input_size.map(|v| v as i64);
        let out = geom.output_size(input_size)?;
        let taps = (geom.kernel[0] * geom.kernel[1]) as usize;
        if geom.kernel != offsets.kernel.map(|v| v as i64)
            || out != offsets.output_size.map(|v| v as i64)
            || offsets.data.len() != 2 * taps * offsets.output_size[0] * offsets.output_size[1]
        {
            return Err(Error::InvalidArgument(format!(
                "offsets of a {:?} kernel, {} values for a {:?} output, do not fit {geom:?} on a \
                 {input_size:?} input (output {out:?})",
                offsets.kernel,
                offsets.data.len(),
                offsets.output_size
            )));
        }
        let layout = Layout {
            h: input_size[0],
            w: input_size[1],
            ho: out[0],
            wo: out[1],
            geom,
            per_item: false,
            border,
        };
        layout.build(&offsets.data, None, kind)
    }

    /// The same plan with its tensors on `device` (shared, not copied, if already there). On a
    /// device other than the CPU the plan keeps the corner indices of the ATen path (the
    /// top-left corners stay on the CPU).
    pub fn to_device(&self, device: Device) -> Self {
        if device == self.device() {
            return self.shallow_clone();
        }
        SamplingPlan {
            index: (device != Device::Cpu).then(|| self.corner_index().to_device(device)),
            top_left: self.top_left.shallow_clone(),
            frac: self.frac.to_device(device),
            rows: self.rows.shallow_clone(),
            ..*self
        }
    }

    /// Another handle on the same tensors (no copy; libtorch reference counting).
    pub fn shallow_clone(&self) -> Self {
        SamplingPlan {
            index: self.index.as_ref().map(Tensor::shallow_clone),
            top_left: self.top_left.shallow_clone(),
            frac: self.frac.shallow_clone(),
            rows: self.rows.shallow_clone(),
            ..*self
        }
    }

    /// Whether two plans hold the same tensor storage.
    pub fn shares_storage_with(&self, other: &SamplingPlan) -> bool {
        self.frac.data_ptr() == other.frac.data_ptr()
    }

    /// Output size `[H_out, W_out]`.
    pub fn output_size(&self) -> [i64; 2] {
        self.output_size
    }

    /// Input size `[H, W]`.
    pub fn input_size(&self) -> [i64; 2] {
        self.input_size
    }

    /// Kernel size `[kh, kw]`.
    pub fn kernel(&self) -> [i64; 2] {
        self.kernel
    }

    /// `Some(B)` for a plan built from per-item offsets.
    pub fn batch(&self) -> Option<i64> {
        self.batch
    }

    /// Device of the plan's tensors.
    pub fn device(&self) -> Device {
        self.frac.device()
    }

    /// Kind of the plan's fractions (and weights).
    pub fn kind(&self) -> Kind {
        self.frac.kind()
    }

    /// The fractions `(ly, lx)` `[N * 2]` (on the plan's device).
    pub fn frac(&self) -> &Tensor {
        &self.frac
    }

    /// The four bilinear corners of every sample, `[N * 4]` int32 (top-left, top-right,
    /// bottom-left, bottom-right) as flat indices into the stacked `[H*W + 1]`-row tables of the
    /// ATen path, on the plan's device. A CPU plan derives them from its top-left corners on
    /// each call (one parallel pass; the native kernels never need them), a plan on another
    /// device keeps them.
    pub fn corner_index(&self) -> Tensor {
        if let Some(index) = &self.index {
            return index.shallow_clone();
        }
        let tl = elements::<i32>(&self.top_left)
            .expect("a plan's top-left corners are a contiguous int32 CPU tensor");
        filled::<i32>(4 * tl.len(), |out| {
            corners_of_top_left(tl, self.input_size, self.border, out)
        })
    }

    /// `[N]` (int32, CPU): each sample's top-left corner in the padded input (see the type's
    /// documentation and [`padded_size`]).
    pub fn top_left(&self) -> &Tensor {
        &self.top_left
    }

    /// What the samples read outside the input.
    pub fn border(&self) -> Border {
        self.border
    }

    /// The bilinear corner weights `[N * 4]` in `kind`, in the order of the corner indices:
    /// `(1-ly)(1-lx), (1-ly)lx, ly(1-lx), ly lx` (on the plan's device).
    pub fn f_weights(&self, kind: Kind) -> Result<Tensor> {
        let frac = self.frac.f_to_kind(kind)?.f_view([-1, 2])?;
        let (ly, lx) = (frac.f_select(1, 0)?, frac.f_select(1, 1)?);
        let (hy, hx) = (
            ly.f_neg()?.f_add_scalar(1.0)?,
            lx.f_neg()?.f_add_scalar(1.0)?,
        );
        Ok(Tensor::f_stack(
            &[
                hy.f_mul(&hx)?,
                hy.f_mul(&lx)?,
                ly.f_mul(&hx)?,
                ly.f_mul(&lx)?,
            ],
            1,
        )?
        .f_view([-1])?)
    }

    /// `[items, H_out, 2]` (int32, CPU): the lowest and highest input row read by each output
    /// row (lowest > highest where it reads none).
    pub fn rows(&self) -> &Tensor {
        &self.rows
    }

    /// Bytes held by the plan's tensors.
    pub fn memory_bytes(&self) -> usize {
        [
            Some(&self.top_left),
            Some(&self.frac),
            Some(&self.rows),
            self.index.as_ref(),
        ]
        .into_iter()
        .flatten()
        .map(|t| t.numel() * t.kind().elt_size_in_bytes())
        .sum()
    }

    /// The column matrix of `input`: for each output pixel, the bilinear samples of every tap
    /// and channel (the ATen path; any device).
    ///
    /// # Shapes
    /// - `input`: `[B, C, H, W]`
    /// - output: `[B, H_out * W_out, K, C]` (pixel-major, then tap, then channel)
    pub fn f_columns(&self, input: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = self.check_input(input)?;
        let weight = self.f_weights(input.kind())?;
        let (p, k) = (
            self.output_size[0] * self.output_size[1],
            self.kernel[0] * self.kernel[1],
        );
        let index = self.corner_index();
        let n = index.numel() as i64 / 4;
        let bags = Tensor::f_arange_start_step(0, 4 * n, 4, (Kind::Int, self.device()))?;
        let bag = |table: &Tensor| -> Result<Tensor> {
            let (sum, _, _, _) = Tensor::f_embedding_bag(
                table,
                &index,
                &bags,
                false,
                0, // mode: sum
                false,
                Some(&weight),
                false,
            )?;
            Ok(sum)
        };
        match self.batch {
            None => {
                // Table [H*W + 1, B*C]: one row per pixel holding every item's channels, so the
                // shared plan serves the whole batch without copying indices.
                let table = input.f_permute([2, 3, 0, 1])?.f_reshape([h * w, b * c])?;
                let zero = Tensor::f_zeros([1, b * c], (input.kind(), input.device()))?;
                let table = Tensor::f_cat(&[table, zero], 0)?;
                Ok(bag(&table)?.f_view([p, k, b, c])?.f_permute([2, 0, 1, 3])?)
            }
            Some(_) => {
                // Table [B*(H*W + 1), C]: items stacked, each followed by its zero row.
                let table = input.f_permute([0, 2, 3, 1])?.f_reshape([b, h * w, c])?;
                let zero = Tensor::f_zeros([b, 1, c], (input.kind(), input.device()))?;
                let table = Tensor::f_cat(&[table, zero], 1)?.f_reshape([b * (h * w + 1), c])?;
                Ok(bag(&table)?.f_view([b, p, k, c])?)
            }
        }
    }

    /// Checks that `input` fits the plan: float, `[B, C, H, W]` with the plan's `H, W` (and `B`
    /// for per-item plans), on the plan's device. Returns `(B, C, H, W)`.
    pub(crate) fn check_input(&self, input: &Tensor) -> Result<(i64, i64, i64, i64)> {
        check_float(input, "input")?;
        let (b, c, h, w) = input.size4().map_err(|_| {
            Error::InvalidArgument(format!(
                "input must be [B, C, H, W], got {:?}",
                input.size()
            ))
        })?;
        if [h, w] != self.input_size {
            return Err(Error::InvalidArgument(format!(
                "input is {h}x{w} but the offsets were built for {}x{}",
                self.input_size[0], self.input_size[1]
            )));
        }
        if input.device() != self.device() {
            return Err(Error::InvalidArgument(format!(
                "input is on {:?} but the sampling plan is on {:?}",
                input.device(),
                self.device()
            )));
        }
        if let Some(pb) = self.batch {
            if pb != b {
                return Err(Error::InvalidArgument(format!(
                    "offsets have batch {pb} but input has batch {b}"
                )));
            }
        }
        Ok((b, c, h, w))
    }
}

/// Whether this thread's tests asked for the portable [`fill_row_zeros`] (never outside tests):
/// the test of the fill holds both clones to the per-sample rule on a CPU with AVX2.
fn portable_fill_only() -> bool {
    #[cfg(test)]
    {
        tests::PORTABLE_FILL.with(|p| p.get())
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

/// The four bilinear corners of every sample (`[top_left.len() * 4]`: top-left, top-right,
/// bottom-left, bottom-right) as flat indices into the stacked `[H*W + 1]`-row tables of the
/// ATen path (an item's zero row last), from the samples' top-left corners in the padded input
/// (see [`SamplingPlan`]): corners off the input, and every corner of a sample outside, are the
/// zero row; with [`Border::WrapX`] the right corner of the last column is column 0.
fn corners_of_top_left(top_left: &[i32], [h, w]: [i64; 2], border: Border, out: &mut [i32]) {
    let [hp, wp] = padded_size([h, w]);
    let (frame, blank) = (hp * wp, (h + 1) * wp);
    let wrap = border == Border::WrapX;
    out.par_chunks_mut(4 * 4096)
        .zip(top_left.par_chunks(4096))
        .for_each(|(out, tl)| {
            for (c, &t) in out.chunks_exact_mut(4).zip(tl) {
                let (item, r) = (t as i64 / frame, t as i64 % frame);
                let base = item * (h * w + 1);
                let zero = (base + h * w) as i32;
                if r == blank {
                    c.fill(zero);
                    continue;
                }
                let (y0, x0) = (r / wp - 1, r % wp - 1);
                let x1 = if wrap && x0 + 1 == w { 0 } else { x0 + 1 };
                let at = |y: i64, x: i64| {
                    if y >= 0 && y < h && x >= 0 && x < w {
                        (base + y * w + x) as i32
                    } else {
                        zero
                    }
                };
                c.copy_from_slice(&[at(y0, x0), at(y0, x1), at(y0 + 1, x0), at(y0 + 1, x1)]);
            }
        });
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
fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::{corners_of_top_left, floor, padded_size, Border, ConvGeometry, Layout};

    thread_local! {
        /// Set by a test: `Layout::fill_row` takes the portable fill even where AVX2 is there.
        pub(super) static PORTABLE_FILL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    }

    /// torchvision's bilinear interpolation with zeros outside, as (flat index or `None` for an
    /// out-of-range corner, weight) for the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1). With
    /// [`Border::WrapX`] corner columns are taken modulo `w` (never out of range).
    fn bilinear_border(y: f64, x: f64, h: i64, w: i64, border: Border) -> [(Option<i64>, f64); 4] {
        let wrap = border == Border::WrapX;
        let x_outside = !wrap && (x <= -1.0 || x >= w as f64);
        if y <= -1.0 || y >= h as f64 || x_outside || !y.is_finite() || !x.is_finite() {
            return [(None, 0.0); 4];
        }
        let (y0, x0) = (floor(y) as i64, floor(x) as i64);
        let (ly, lx) = (y - y0 as f64, x - x0 as f64);
        let (hy, hx) = (1.0 - ly, 1.0 - lx);
        let at = |yy: i64, xx: i64| {
            let xx = if wrap { xx.rem_euclid(w) } else { xx };
            (yy >= 0 && yy < h && xx >= 0 && xx < w).then_some(yy * w + xx)
        };
        [
            (at(y0, x0), hy * hx),
            (at(y0, x0 + 1), hy * lx),
            (at(y0 + 1, x0), ly * hx),
            (at(y0 + 1, x0 + 1), ly * lx),
        ]
    }

    /// The corners and fractions of one sample as the plan stores them, from [`bilinear_border`].
    fn reference_sample(
        y: f64,
        x: f64,
        h: i64,
        w: i64,
        border: Border,
        base: i64,
    ) -> ([i32; 4], [f64; 2]) {
        let corners = bilinear_border(y, x, h, w, border);
        let idx = corners.map(|(flat, _)| (base + flat.unwrap_or(h * w)) as i32);
        if corners.iter().any(|(flat, _)| flat.is_some()) {
            (idx, [y - floor(y), x - floor(x)])
        } else {
            (idx, [0.0, 0.0])
        }
    }

    #[test]
    fn fill_row_matches_bilinear_sample_by_sample() {
        // Offsets around and past the border, non-finite ones, strides, dilations, padding,
        // per-item offsets and both border rules.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let specials = [
            f64::NAN,
            f64::INFINITY,
            -f64::INFINITY,
            -1.0,
            0.0,
            1e12,
            -1e12,
        ];
        for (case, &(h, w, kernel, stride, padding, dilation, items, border)) in [
            (7, 9, [3, 3], [1, 1], [1, 1], [1, 1], None, Border::Zeros),
            (
                6,
                11,
                [3, 5],
                [2, 1],
                [0, 2],
                [1, 2],
                Some(2),
                Border::Zeros,
            ),
            (5, 8, [3, 3], [1, 2], [1, 1], [2, 1], None, Border::WrapX),
            (4, 6, [1, 3], [1, 1], [0, 1], [1, 1], Some(3), Border::WrapX),
        ]
        .iter()
        .enumerate()
        {
            let geom = ConvGeometry::new(kernel, stride, padding, dilation);
            let [ho, wo] = geom.output_size([h, w]).unwrap();
            let taps = (kernel[0] * kernel[1]) as usize;
            let n_items = items.unwrap_or(1);
            let plane = (ho * wo) as usize;
            let off: Vec<f64> = (0..n_items as usize * 2 * taps * plane)
                .map(|i| {
                    if i % 23 == 5 {
                        specials[i / 23 % specials.len()]
                    } else {
                        // Mostly within a few pixels, sometimes far outside.
                        let spread = if i % 7 == 0 {
                            3.0 * (h + w) as f64
                        } else {
                            3.0
                        };
                        (next() - 0.5) * 2.0 * spread
                    }
                })
                .collect();
            let layout = Layout {
                h,
                w,
                ho,
                wo,
                geom,
                per_item: items.is_some(),
                border,
            };
            let row = wo as usize * taps;
            // Both clones of the fill without wrap (AVX2 where the CPU has it, and portable).
            for (r, portable) in (0..(n_items * ho) as usize).flat_map(|r| [(r, false), (r, true)])
            {
                let mut idx = vec![-7i32; 4 * row];
                let mut frac = vec![-7.0f64; 2 * row];
                let mut top_left = vec![-7i32; row];
                PORTABLE_FILL.with(|p| p.set(portable));
                let reach = layout.fill_row(&off, r, &mut top_left, &mut frac);
                PORTABLE_FILL.with(|p| p.set(false));
                // The ATen path's corner indices, derived from the top-left corners.
                corners_of_top_left(&top_left, [h, w], border, &mut idx);
                let (item, oy) = (r as i64 / ho, r as i64 % ho);
                let base = if items.is_some() {
                    item * (h * w + 1)
                } else {
                    0
                };
                let [hp, wp] = padded_size([h, w]);
                let padded_base = if items.is_some() { item * hp * wp } else { 0 };
                let mut want_reach = [i32::MAX, i32::MIN];
                for ox in 0..wo {
                    for k in 0..taps as i64 {
                        let (i, j) = (k / kernel[1], k % kernel[1]);
                        let p = (oy * wo + ox) as usize;
                        let at = |c: i64| off[((item * 2 * taps as i64 + c) as usize) * plane + p];
                        let y = (oy * stride[0] - padding[0] + i * dilation[0]) as f64 + at(2 * k);
                        let x =
                            (ox * stride[1] - padding[1] + j * dilation[1]) as f64 + at(2 * k + 1);
                        let (want_idx, want_frac) = reference_sample(y, x, h, w, border, base);
                        let s = (ox * taps as i64 + k) as usize;
                        let what = format!("case {case}, row {r}, ox {ox}, tap {k}: y {y}, x {x}");
                        assert_eq!(idx[4 * s..4 * s + 4], want_idx, "{what}");
                        assert_eq!(frac[2 * s..2 * s + 2], want_frac, "{what}");
                        let inside = want_frac != [0.0, 0.0]
                            || want_idx.iter().any(|&c| c != (base + h * w) as i32);
                        // The padded input: the top-left corner (its column modulo w with
                        // wrap), or the zero block at row h, column -1.
                        let want_top_left = if inside {
                            let x0 = floor(x) as i64;
                            let x0 = if border == Border::WrapX {
                                x0.rem_euclid(w)
                            } else {
                                x0
                            };
                            padded_base + (floor(y) as i64 + 1) * wp + x0 + 1
                        } else {
                            padded_base + (h + 1) * wp
                        };
                        assert_eq!(top_left[s] as i64, want_top_left, "{what}");
                        if inside {
                            let y0 = floor(y) as i32;
                            want_reach = [want_reach[0].min(y0), want_reach[1].max(y0 + 1)];
                        }
                    }
                }
                assert_eq!(reach, want_reach, "case {case}, row {r}");
            }
        }
    }

    fn bilinear(y: f64, x: f64, h: i64, w: i64) -> [(Option<i64>, f64); 4] {
        bilinear_border(y, x, h, w, Border::Zeros)
    }

    #[test]
    fn wrap_x_takes_columns_modulo_the_width() {
        // x = -0.25 on a 5-wide row 1: corners at columns -1 -> 4 and 0, weights 0.25 / 0.75.
        let c = bilinear_border(1.0, -0.25, 4, 5, Border::WrapX);
        assert_eq!((c[0].0, c[1].0), (Some(5 + 4), Some(5)));
        assert!((c[0].1 - 0.25).abs() < 1e-12 && (c[1].1 - 0.75).abs() < 1e-12);
        // Far outside: one period further gives the same corners; rows still read zero.
        let far = bilinear_border(1.0, -0.25 + 10.0, 4, 5, Border::WrapX);
        assert_eq!((far[0].0, far[1].0), (Some(9), Some(5)));
        assert!(bilinear_border(-1.0, 2.0, 4, 5, Border::WrapX)
            .iter()
            .all(|(i, w)| i.is_none() && *w == 0.0));
        // The same sample with zeros outside loses the wrapped corner.
        assert_eq!(bilinear(1.0, -0.25, 4, 5)[0].0, None);
    }

    #[test]
    fn bilinear_weights_sum_to_one_inside() {
        let c = bilinear(1.25, 2.5, 4, 5);
        let total: f64 = c.iter().map(|(_, w)| w).sum();
        assert!((total - 1.0).abs() < 1e-12);
        assert_eq!(c[0].0, Some(5 + 2));
        assert!((c[0].1 - 0.75 * 0.5).abs() < 1e-12);
    }

    #[test]
    fn bilinear_is_zero_outside_and_partial_at_border() {
        assert!(bilinear(-1.0, 0.0, 4, 4)
            .iter()
            .all(|(i, w)| i.is_none() && *w == 0.0));
        assert!(bilinear(0.0, 4.0, 4, 4).iter().all(|(i, _)| i.is_none()));
        // y in (-1, 0): the top corners fall outside, the bottom ones keep weight ly.
        let c = bilinear(-0.5, 1.0, 4, 4);
        assert_eq!(c[0].0, None);
        assert_eq!(c[2].0, Some(1));
        assert!((c[2].1 - 0.5).abs() < 1e-12);
    }
}
