//! The sampling plan: bilinear corner indices and weights of every (output pixel, tap), and its
//! transpose (for every input pixel and tap, the output pixels that sample it).

use std::sync::{Arc, Mutex};

use rayon::prelude::*;
use tch::kind::Element;
use tch::{Device, Kind, Tensor};

use super::check_float;
use crate::error::{Error, Result};

/// Precomputed bilinear sampling of a deformable convolution with fixed offsets.
///
/// For `N = P * K` samples (`P = H_out*W_out` output pixels, `K = kh*kw` taps, pixel-major;
/// times `B` for per-item offsets), `index` `[N * 4]` (int32) holds the flat indices of the four
/// bilinear corners (top-left, top-right, bottom-left, bottom-right) into the input's `H*W`
/// pixels, with one extra zero row at index `H*W` for corners outside the input, and `weight`
/// their bilinear weights (`[N * 4]`). Per-item plans index a table that stacks the items, each
/// followed by its zero row: item `b`'s indices are offset by `b * (H*W + 1)`.
///
/// A column is then one weighted "bag" of four rows of a pixel-major table, which libtorch's
/// `embedding_bag` computes (and differentiates) in one fused op (the ATen path); the native CPU
/// kernels read the same indices and weights, and for the input gradient a [`Transposed`] plan
/// built from them on first use.
#[derive(Debug)]
pub struct SamplingPlan {
    /// `[N * 4]` int32: four corners per sample.
    index: Tensor,
    /// `[N * 4]`, same order.
    weight: Tensor,
    /// The transpose, built on first need (CPU plans only) and shared by shallow clones.
    transposed: Arc<Mutex<Option<Transposed>>>,
    input_size: [i64; 2],
    output_size: [i64; 2],
    kernel: [i64; 2],
    /// `Some(B)` for per-item offsets.
    batch: Option<i64>,
}

/// The transposed sampling plan in CSR form: for every (plan item, tap `k`, input pixel `q`),
/// row `(item * K + k) * H*W + q`, the entries `ptr[row] .. ptr[row + 1]` of `src` (output
/// pixel `p` within the item) and `weight` (the bilinear weight with which sample `(p, k)` reads
/// pixel `q`). Corners outside the input and corners of weight exactly 0 have no entry. Entries of
/// a row are in increasing `p`.
#[derive(Debug)]
pub struct Transposed {
    /// `[items * K * H*W + 1]` int32 row starts.
    pub ptr: Tensor,
    /// `[E]` int32 output pixels.
    pub src: Tensor,
    /// `[E]` weights, in the plan's kind.
    pub weight: Tensor,
}

impl Transposed {
    fn shallow_clone(&self) -> Self {
        Transposed {
            ptr: self.ptr.shallow_clone(),
            src: self.src.shallow_clone(),
            weight: self.weight.shallow_clone(),
        }
    }
}

/// Plan weights: float32 or float64.
trait PlanFloat: Element + Copy + Send + Sync + PartialEq {
    fn from_f64(v: f64) -> Self;
    fn zero() -> Self;
}
impl PlanFloat for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn zero() -> Self {
        0.0
    }
}
impl PlanFloat for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
    fn zero() -> Self {
        0.0
    }
}

/// A new contiguous CPU tensor of `n` elements of `T`, its memory filled by `fill`.
fn filled<T: Element>(n: usize, fill: impl FnOnce(&mut [T])) -> Tensor {
    let t = Tensor::empty([n as i64], (T::KIND, Device::Cpu));
    // SAFETY: `t` is a fresh contiguous CPU tensor of exactly `n` elements of `T` (same size as
    // `T::KIND`, the contract of `Element`); nothing else refers to its memory while `fill` runs.
    let data = unsafe { elements_mut::<T>(&t, n) };
    fill(data);
    t
}

/// The elements of a contiguous CPU tensor of `n` elements of `T`.
///
/// # Safety
/// `t` must be a contiguous CPU tensor of `n` elements of kind `T::KIND`, and no other reference
/// to its memory may be used while the slice lives.
unsafe fn elements_mut<T: Element>(t: &Tensor, n: usize) -> &mut [T] {
    if n == 0 {
        return &mut [];
    }
    std::slice::from_raw_parts_mut(t.data_ptr() as *mut T, n)
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
    kernel: [i64; 2],
    stride: [i64; 2],
    padding: [i64; 2],
    dilation: [i64; 2],
    per_item: bool,
}

impl Layout {
    /// Fills the corners and weights of the `wo * K` samples of output row `row` (item-major:
    /// `row = item * H_out + oy`) from the offsets `off` (`[items, 2K, H_out, W_out]`).
    fn fill_row<O: Copy + Into<f64>, W: PlanFloat>(
        &self,
        off: &[O],
        row: usize,
        idx: &mut [i32],
        wts: &mut [W],
    ) {
        let (ho, wo, h, w) = (self.ho, self.wo, self.h, self.w);
        let [kh, kw] = self.kernel;
        let taps = (kh * kw) as usize;
        let plane = (ho * wo) as usize;
        let (item, oy) = (row as i64 / ho, row as i64 % ho);
        // Per-item tables stack the items' pixels, each followed by its zero row.
        let base = if self.per_item { item * (h * w + 1) } else { 0 };
        let item_off = &off[item as usize * 2 * taps * plane..];
        let mut s = 0;
        for ox in 0..wo {
            let p = (oy * wo + ox) as usize;
            for i in 0..kh {
                for j in 0..kw {
                    let k = (i * kw + j) as usize;
                    let y = (oy * self.stride[0] - self.padding[0] + i * self.dilation[0]) as f64
                        + item_off[2 * k * plane + p].into();
                    let x = (ox * self.stride[1] - self.padding[1] + j * self.dilation[1]) as f64
                        + item_off[(2 * k + 1) * plane + p].into();
                    for (flat, wt) in bilinear(y, x, h, w) {
                        idx[s] = (base + flat.unwrap_or(h * w)) as i32;
                        wts[s] = W::from_f64(wt);
                        s += 1;
                    }
                }
            }
        }
    }
}

impl SamplingPlan {
    /// Builds the plan from offsets `[2*kh*kw, H_out, W_out]` or `[B, 2*kh*kw, H_out, W_out]`
    /// for an input of `input_size = [H, W]`; weights are stored in `kind` (float32 or
    /// float64), tensors on the CPU. Runs in parallel over output rows.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        offsets: &Tensor,
        input_size: [i64; 2],
        kernel: [i64; 2],
        stride: [i64; 2],
        padding: [i64; 2],
        dilation: [i64; 2],
        kind: Kind,
    ) -> Result<Self> {
        let [h, w] = input_size;
        let [kh, kw] = kernel;
        if kh < 1
            || kw < 1
            || h < 1
            || w < 1
            || stride.iter().chain(&dilation).any(|&v| v < 1)
            || padding.iter().any(|&p| p < 0)
        {
            return Err(Error::InvalidArgument(format!(
                "input {input_size:?}, kernel {kernel:?}, stride {stride:?}, padding {padding:?}, \
                 dilation {dilation:?}: sizes, strides and dilations must be >= 1, padding >= 0"
            )));
        }
        if !matches!(kind, Kind::Float | Kind::Double) {
            return Err(Error::InvalidArgument(format!(
                "plan weights must be float32 or float64, got {kind:?}"
            )));
        }
        let out_dim = |a: usize| {
            (input_size[a] + 2 * padding[a] - dilation[a] * (kernel[a] - 1) - 1) / stride[a] + 1
        };
        let (ho, wo) = (out_dim(0), out_dim(1));
        if ho < 1 || wo < 1 {
            return Err(Error::InvalidArgument(format!(
                "kernel {kernel:?} with padding {padding:?}, dilation {dilation:?} does not fit a \
                 {h}x{w} input"
            )));
        }
        check_float(offsets, "offsets")?;
        let taps = kh * kw;
        let batch = match offsets.size().as_slice() {
            [c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] => None,
            [b, c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] && *b >= 1 => Some(*b),
            other => {
                return Err(Error::InvalidArgument(format!(
                    "offsets must be [{}, {ho}, {wo}] or [B, {}, {ho}, {wo}] for a {kh}x{kw} \
                     kernel on a {h}x{w} input, got {other:?}",
                    2 * taps,
                    2 * taps
                )))
            }
        };
        let items = batch.unwrap_or(1);
        let n = (items * ho * wo * taps * 4) as usize;
        // Indices and entry counts are int32 (half the memory of int64); refuse what overflows.
        if items * (h * w + 1) > i32::MAX as i64 || n > i32::MAX as usize {
            return Err(Error::InvalidArgument(format!(
                "a sampling plan of {items} x {ho}x{wo} x {taps} samples on a {h}x{w} input is \
                 too large for int32 indices"
            )));
        }
        let layout = Layout {
            h,
            w,
            ho,
            wo,
            kernel,
            stride,
            padding,
            dilation,
            per_item: batch.is_some(),
        };
        let off = offsets.to_device(Device::Cpu).contiguous();
        let row_len = (wo * taps * 4) as usize;
        let index = Tensor::empty([n as i64], (Kind::Int, Device::Cpu));
        // SAFETY: `index` is a fresh contiguous int32 CPU tensor of `n` elements, only written
        // through this slice (by disjoint row chunks) until it is moved into the plan.
        let idx = unsafe { elements_mut::<i32>(&index, n) };
        fn fill<O: Copy + Into<f64> + Element + Sync, W: PlanFloat>(
            layout: &Layout,
            off: &Tensor,
            idx: &mut [i32],
            row_len: usize,
            n: usize,
        ) -> Result<Tensor> {
            let off = elements::<O>(off)?;
            Ok(filled::<W>(n, |wts| {
                idx.par_chunks_mut(row_len)
                    .zip(wts.par_chunks_mut(row_len))
                    .enumerate()
                    .for_each(|(row, (i, w))| layout.fill_row(off, row, i, w));
            }))
        }
        let weight = match (off.kind(), kind) {
            (Kind::Float, Kind::Float) => fill::<f32, f32>(&layout, &off, idx, row_len, n)?,
            (Kind::Float, _) => fill::<f32, f64>(&layout, &off, idx, row_len, n)?,
            (_, Kind::Float) => fill::<f64, f32>(&layout, &off, idx, row_len, n)?,
            _ => fill::<f64, f64>(&layout, &off, idx, row_len, n)?,
        };
        Ok(SamplingPlan {
            index,
            weight,
            transposed: Arc::default(),
            input_size,
            output_size: [ho, wo],
            kernel,
            batch,
        })
    }

    /// The same plan with its tensors on `device` (shared, not copied, if already there).
    pub fn to_device(&self, device: Device) -> Self {
        if device == self.device() {
            return self.shallow_clone();
        }
        SamplingPlan {
            index: self.index.to_device(device),
            weight: self.weight.to_device(device),
            transposed: Arc::default(),
            ..*self
        }
    }

    /// Another handle on the same tensors (no copy; libtorch reference counting).
    pub fn shallow_clone(&self) -> Self {
        SamplingPlan {
            index: self.index.shallow_clone(),
            weight: self.weight.shallow_clone(),
            transposed: Arc::clone(&self.transposed),
            ..*self
        }
    }

    /// Whether two plans hold the same tensor storage.
    pub fn shares_storage_with(&self, other: &SamplingPlan) -> bool {
        self.index.data_ptr() == other.index.data_ptr()
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
        self.index.device()
    }

    /// Kind of the plan's weights.
    pub fn kind(&self) -> Kind {
        self.weight.kind()
    }

    /// The corner indices `[N * 4]` (int32) and weights `[N * 4]`.
    pub fn samples(&self) -> (&Tensor, &Tensor) {
        (&self.index, &self.weight)
    }

    /// Bytes held by the plan's tensors, its transpose included once built.
    pub fn memory_bytes(&self) -> usize {
        let bytes = |t: &Tensor| t.numel() * t.kind().elt_size_in_bytes();
        let transposed = self
            .transposed
            .lock()
            .expect("sampling plan lock poisoned")
            .as_ref()
            .map_or(0, |t| bytes(&t.ptr) + bytes(&t.src) + bytes(&t.weight));
        bytes(&self.index) + bytes(&self.weight) + transposed
    }

    /// Builds now what the native CPU kernels otherwise build on first need (the transposed
    /// plan, for input gradients). A no-op for plans on other devices.
    pub fn prepare_native(&self) -> Result<()> {
        if self.device() == Device::Cpu {
            self.transposed()?;
        }
        Ok(())
    }

    /// The transposed plan (CPU plans only), built on first call and kept.
    pub fn transposed(&self) -> Result<Transposed> {
        let mut slot = self.transposed.lock().expect("sampling plan lock poisoned");
        if let Some(t) = slot.as_ref() {
            return Ok(t.shallow_clone());
        }
        let t = match self.weight.kind() {
            Kind::Float => self.build_transposed::<f32>()?,
            _ => self.build_transposed::<f64>()?,
        };
        *slot = Some(t.shallow_clone());
        Ok(t)
    }

    /// Counting sort of the corners by (item, tap, input pixel), in parallel over (item, tap).
    fn build_transposed<W: PlanFloat>(&self) -> Result<Transposed> {
        let index = elements::<i32>(&self.index)?;
        let weight = elements::<W>(&self.weight)?;
        let hw = (self.input_size[0] * self.input_size[1]) as usize;
        let taps = (self.kernel[0] * self.kernel[1]) as usize;
        let p = (self.output_size[0] * self.output_size[1]) as usize;
        let items = self.batch.unwrap_or(1) as usize;
        let per_item = self.batch.is_some();
        let blocks = items * taps;
        // The corners of (item, tap) block `blk` that land in the input: (pixel, output pixel,
        // weight), in increasing output pixel.
        let corners = |blk: usize| {
            let (item, k) = (blk / taps, blk % taps);
            let shift = if per_item { item * (hw + 1) } else { 0 };
            (0..p).flat_map(move |pp| {
                let s = ((item * p + pp) * taps + k) * 4;
                (s..s + 4).filter_map(move |c| {
                    let q = index[c] as usize - shift;
                    (q != hw && weight[c] != W::zero()).then_some((q, pp as i32, weight[c]))
                })
            })
        };
        let ptr = filled::<i32>(blocks * hw + 1, |ptr| {
            // Pass 1: counts per row, then exclusive prefix sums within each block.
            let totals: Vec<usize> = ptr[..blocks * hw]
                .par_chunks_mut(hw.max(1))
                .enumerate()
                .map(|(blk, rows)| {
                    rows.fill(0);
                    for (q, _, _) in corners(blk) {
                        rows[q] += 1;
                    }
                    let mut sum = 0usize;
                    for r in rows.iter_mut() {
                        let c = *r as usize;
                        *r = sum as i32;
                        sum += c;
                    }
                    sum
                })
                .collect();
            // Block bases.
            let mut bases = Vec::with_capacity(blocks + 1);
            let mut acc = 0usize;
            for t in &totals {
                bases.push(acc);
                acc += t;
            }
            ptr[..blocks * hw]
                .par_chunks_mut(hw.max(1))
                .zip(bases.par_iter())
                .for_each(|(rows, &base)| rows.iter_mut().for_each(|r| *r += base as i32));
            ptr[blocks * hw] = acc as i32;
        });
        let starts = elements::<i32>(&ptr)?;
        let total = starts[blocks * hw] as usize;
        let src = Tensor::empty([total as i64], (Kind::Int, Device::Cpu));
        // SAFETY: fresh contiguous int32 CPU tensor of `total` elements, written only through
        // this slice (split into disjoint per-block chunks) before it is returned.
        let src_all = unsafe { elements_mut::<i32>(&src, total) };
        let weight_t = filled::<W>(total, |wt_all| {
            // Pass 2: place every corner at its row's cursor; blocks own disjoint ranges.
            let mut src_chunks = Vec::with_capacity(blocks);
            let mut wt_chunks = Vec::with_capacity(blocks);
            let (mut src_rest, mut wt_rest) = (&mut src_all[..], &mut wt_all[..]);
            for blk in 0..blocks {
                let len = (starts[(blk + 1) * hw] - starts[blk * hw]) as usize;
                let (a, b) = std::mem::take(&mut src_rest).split_at_mut(len);
                let (c, d) = std::mem::take(&mut wt_rest).split_at_mut(len);
                src_chunks.push(a);
                wt_chunks.push(c);
                src_rest = b;
                wt_rest = d;
            }
            src_chunks
                .into_par_iter()
                .zip(wt_chunks.into_par_iter())
                .enumerate()
                .for_each(|(blk, (src, wt))| {
                    let base = starts[blk * hw] as usize;
                    let mut cursor: Vec<usize> = starts[blk * hw..(blk + 1) * hw]
                        .iter()
                        .map(|&s| s as usize - base)
                        .collect();
                    for (q, pp, w) in corners(blk) {
                        src[cursor[q]] = pp;
                        wt[cursor[q]] = w;
                        cursor[q] += 1;
                    }
                });
        });
        Ok(Transposed {
            ptr,
            src,
            weight: weight_t,
        })
    }

    /// The column matrix of `input`: for each output pixel, the bilinear samples of every tap
    /// and channel (the ATen path; any device).
    ///
    /// # Shapes
    /// - `input`: `[B, C, H, W]`
    /// - output: `[B, H_out * W_out, K, C]` (pixel-major, then tap, then channel)
    pub fn f_columns(&self, input: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = self.check_input(input)?;
        let weight = self.weight.to_kind(input.kind());
        let (p, k) = (
            self.output_size[0] * self.output_size[1],
            self.kernel[0] * self.kernel[1],
        );
        let n = self.index.numel() as i64 / 4;
        let bags = Tensor::f_arange_start_step(0, 4 * n, 4, (Kind::Int, self.device()))?;
        let bag = |table: &Tensor| -> Result<Tensor> {
            let (sum, _, _, _) = Tensor::f_embedding_bag(
                table,
                &self.index,
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

/// torchvision's bilinear interpolation with zeros outside, as (flat index or `None` for an
/// out-of-range corner, weight) for the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1).
fn bilinear(y: f64, x: f64, h: i64, w: i64) -> [(Option<i64>, f64); 4] {
    if y <= -1.0 || y >= h as f64 || x <= -1.0 || x >= w as f64 || !y.is_finite() || !x.is_finite()
    {
        return [(None, 0.0); 4];
    }
    let (y0, x0) = (y.floor() as i64, x.floor() as i64);
    let (ly, lx) = (y - y0 as f64, x - x0 as f64);
    let (hy, hx) = (1.0 - ly, 1.0 - lx);
    let at = |yy: i64, xx: i64| (yy >= 0 && yy < h && xx >= 0 && xx < w).then_some(yy * w + xx);
    [
        (at(y0, x0), hy * hx),
        (at(y0, x0 + 1), hy * lx),
        (at(y0 + 1, x0), ly * hx),
        (at(y0 + 1, x0 + 1), ly * lx),
    ]
}

#[cfg(test)]
mod tests {
    use super::bilinear;

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
