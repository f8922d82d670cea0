//! The sampling plan: bilinear corner indices and weights of every (tap, output pixel).

use rayon::prelude::*;
use tch::{Device, Kind, Tensor};

use super::check_float;
use crate::error::{Error, Result};

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

/// Precomputed bilinear sampling of a deformable convolution with fixed offsets.
///
/// For `N = P * K` samples (`P = H_out*W_out` output pixels, `K = kh*kw` taps, pixel-major;
/// times `B` for per-item offsets), `index` `[N * 4]` holds the flat indices of the four bilinear
/// corners (top-left, top-right, bottom-left, bottom-right) into the input's `H*W` pixels, with
/// one extra zero row at index `H*W` for corners outside the input, and `weight` their
/// bilinear weights (`[N * 4]`). A column is then one weighted "bag" of four rows of a pixel-major table,
/// which libtorch's `embedding_bag` computes (and differentiates) in one fused op.
#[derive(Debug)]
pub struct SamplingPlan {
    /// `[N * 4]`: four corners per sample.
    index: Tensor,
    /// `[N * 4]`, same order.
    weight: Tensor,
    /// `[N]`: start of each sample's bag of four in `index` (0, 4, 8, ...).
    bags: Tensor,
    input_size: [i64; 2],
    output_size: [i64; 2],
    kernel: [i64; 2],
    /// `Some(B)` for per-item offsets.
    batch: Option<i64>,
}

impl SamplingPlan {
    /// Builds the plan from offsets `[2*kh*kw, H_out, W_out]` or `[B, 2*kh*kw, H_out, W_out]`
    /// for an input of `input_size = [H, W]`; weights are stored in `kind`, tensors on the CPU.
    /// Zeros outside the input (torchvision); see [`SamplingPlan::with_border`].
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
        Self::with_border(
            offsets,
            input_size,
            kernel,
            stride,
            padding,
            dilation,
            kind,
            Border::Zeros,
        )
    }

    /// [`SamplingPlan::new`] with a choice of what is read outside the input: with
    /// [`Border::WrapX`] the convolution's horizontal zero padding reads the other side of the
    /// image as well (circular padding in x).
    #[allow(clippy::too_many_arguments)]
    pub fn with_border(
        offsets: &Tensor,
        input_size: [i64; 2],
        kernel: [i64; 2],
        stride: [i64; 2],
        padding: [i64; 2],
        dilation: [i64; 2],
        kind: Kind,
        border: Border,
    ) -> Result<Self> {
        let [h, w] = input_size;
        let [kh, kw] = kernel;
        if kh < 1
            || kw < 1
            || stride.iter().chain(&dilation).any(|&v| v < 1)
            || padding.iter().any(|&p| p < 0)
        {
            return Err(Error::InvalidArgument(format!(
                "kernel {kernel:?}, stride {stride:?}, padding {padding:?}, dilation {dilation:?}: \
                 sizes, strides and dilations must be >= 1, padding >= 0"
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
            [b, c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] => Some(*b),
            other => {
                return Err(Error::InvalidArgument(format!(
                    "offsets must be [{}, {ho}, {wo}] or [B, {}, {ho}, {wo}] for a {kh}x{kw} \
                     kernel on a {h}x{w} input, got {other:?}",
                    2 * taps,
                    2 * taps
                )))
            }
        };
        let off: Vec<f64> = Vec::<f64>::try_from(
            offsets
                .to_device(Device::Cpu)
                .to_kind(Kind::Double)
                .contiguous()
                .view(-1),
        )?;
        let items = batch.unwrap_or(1);
        let plane = (ho * wo) as usize;
        let taps_u = taps as usize;
        // One output row of one item per task: (indices, weights), 4 per sample.
        let rows: Vec<(Vec<i64>, Vec<f64>)> = (0..items * ho)
            .into_par_iter()
            .map(|row| {
                let (item, oy) = (row / ho, row % ho);
                // Per-item tables stack the items' pixels, each followed by its zero row.
                let base = if batch.is_some() {
                    item * (h * w + 1)
                } else {
                    0
                };
                let item_off = &off[item as usize * 2 * taps_u * plane..];
                let mut idx = Vec::with_capacity(wo as usize * taps_u * 4);
                let mut wts = Vec::with_capacity(wo as usize * taps_u * 4);
                for ox in 0..wo {
                    let p = (oy * wo + ox) as usize;
                    for i in 0..kh {
                        for j in 0..kw {
                            let k = (i * kw + j) as usize;
                            let y = (oy * stride[0] - padding[0] + i * dilation[0]) as f64
                                + item_off[2 * k * plane + p];
                            let x = (ox * stride[1] - padding[1] + j * dilation[1]) as f64
                                + item_off[(2 * k + 1) * plane + p];
                            for (flat, wt) in bilinear(y, x, h, w, border) {
                                idx.push(base + flat.unwrap_or(h * w));
                                wts.push(wt);
                            }
                        }
                    }
                }
                (idx, wts)
            })
            .collect();
        let n = items * ho * wo * taps;
        let (idx, wts): (Vec<i64>, Vec<f64>) = (
            rows.iter().flat_map(|r| r.0.iter().copied()).collect(),
            rows.iter().flat_map(|r| r.1.iter().copied()).collect(),
        );
        Ok(SamplingPlan {
            index: Tensor::from_slice(&idx),
            weight: Tensor::from_slice(&wts).to_kind(kind),
            bags: Tensor::arange_start_step(0, 4 * n, 4, (Kind::Int64, Device::Cpu)),
            input_size,
            output_size: [ho, wo],
            kernel,
            batch,
        })
    }

    /// The same plan with its tensors on `device`.
    pub fn to_device(&self, device: Device) -> Self {
        SamplingPlan {
            index: self.index.to_device(device),
            weight: self.weight.to_device(device),
            bags: self.bags.to_device(device),
            ..*self
        }
    }

    /// Another handle on the same tensors (no copy; libtorch reference counting).
    pub fn shallow_clone(&self) -> Self {
        SamplingPlan {
            index: self.index.shallow_clone(),
            weight: self.weight.shallow_clone(),
            bags: self.bags.shallow_clone(),
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

    /// Device of the plan's tensors.
    pub fn device(&self) -> Device {
        self.index.device()
    }

    /// The column matrix of `input`: for each output pixel, the bilinear samples of every tap
    /// and channel.
    ///
    /// # Shapes
    /// - `input`: `[B, C, H, W]`
    /// - output: `[B, H_out * W_out, K, C]` (pixel-major, then tap, then channel)
    pub fn f_columns(&self, input: &Tensor) -> Result<Tensor> {
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
        let weight = self.weight.to_kind(input.kind());
        let (p, k) = (
            self.output_size[0] * self.output_size[1],
            self.kernel[0] * self.kernel[1],
        );
        let bag = |table: &Tensor| -> Result<Tensor> {
            let (sum, _, _, _) = Tensor::f_embedding_bag(
                table,
                &self.index,
                &self.bags,
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
            Some(pb) => {
                if pb != b {
                    return Err(Error::InvalidArgument(format!(
                        "offsets have batch {pb} but input has batch {b}"
                    )));
                }
                // Table [B*(H*W + 1), C]: items stacked, each followed by its zero row.
                let table = input.f_permute([0, 2, 3, 1])?.f_reshape([b, h * w, c])?;
                let zero = Tensor::f_zeros([b, 1, c], (input.kind(), input.device()))?;
                let table = Tensor::f_cat(&[table, zero], 1)?.f_reshape([b * (h * w + 1), c])?;
                Ok(bag(&table)?.f_view([b, p, k, c])?)
            }
        }
    }
}

/// torchvision's bilinear interpolation with zeros outside, as (flat index or `None` for an
/// out-of-range corner, weight) for the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1). With
/// [`Border::WrapX`] corner columns are taken modulo `w` (never out of range).
fn bilinear(y: f64, x: f64, h: i64, w: i64, border: Border) -> [(Option<i64>, f64); 4] {
    let wrap = border == Border::WrapX;
    let x_outside = !wrap && (x <= -1.0 || x >= w as f64);
    if y <= -1.0 || y >= h as f64 || x_outside || !y.is_finite() || !x.is_finite() {
        return [(None, 0.0); 4];
    }
    let (y0, x0) = (y.floor() as i64, x.floor() as i64);
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

#[cfg(test)]
mod tests {
    use super::{bilinear as bilinear_border, Border};

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
