//! The sampling plan: bilinear corner indices and weights of every (output pixel, tap).
//!
//! Submodules: `fill` builds the plan (torchvision's bilinear rule, row by row, in parallel);
//! `tests` holds it to a per-sample reference.

mod fill;
#[cfg(test)]
mod tests;

use rayon::prelude::*;
use tch::{Device, Kind, Tensor};

// `padded_size([H, W]) = [H + 3, W + 2]`: the size of an `[H, W]` input padded as the plan's
// `top_left` indices read it (one row above and two below, one column on each side).
use calibconv_geometry::plan::padded_size;

use super::{check_float, size4, INPUT_DIMS};
use crate::error::{Error, Result};
use crate::kernel::Offsets;
use fill::{elements, filled, Layout};

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
/// column on each side (`(H + 3) x (W + 2)` pixels, `padded_size`; per-item plans index the
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
    /// documentation and `padded_size`).
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
        let (b, c, h, w) = size4(input, "input", INPUT_DIMS)?;
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
