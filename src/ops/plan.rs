//! The sampling plan: bilinear corner indices and weights of every (tap, output pixel).

use tch::{Device, Kind, Tensor};

use super::check_float;
use crate::error::{Error, Result};

/// Precomputed bilinear sampling of a deformable convolution with fixed offsets.
///
/// For `N = K * P` samples (`K = kh*kw` taps, `P = H_out*W_out` pixels; times `B` for
/// per-item offsets), `index` holds four `[N]` int64 tensors (corners top-left, top-right,
/// bottom-left, bottom-right) into the flattened input `H*W` with one extra zero element at
/// index `H*W`, and `weight` four `[N]` tensors of bilinear weights.
#[derive(Debug)]
pub struct SamplingPlan {
    index: [Tensor; 4],
    weight: [Tensor; 4],
    input_size: [i64; 2],
    output_size: [i64; 2],
    kernel: [i64; 2],
    /// `Some(B)` for per-item offsets.
    batch: Option<i64>,
}

impl SamplingPlan {
    /// Builds the plan from offsets `[2*kh*kw, H_out, W_out]` or `[B, 2*kh*kw, H_out, W_out]`
    /// for an input of `input_size = [H, W]`; weights are stored in `kind`, tensors on the CPU.
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
        if kh < 1 || kw < 1 || stride.iter().chain(&dilation).any(|&v| v < 1) || padding.iter().any(|&p| p < 0) {
            return Err(Error::InvalidArgument(format!(
                "kernel {kernel:?}, stride {stride:?}, padding {padding:?}, dilation {dilation:?}: sizes, strides and dilations must be >= 1, padding >= 0"
            )));
        }
        let out_dim = |a: usize| (input_size[a] + 2 * padding[a] - dilation[a] * (kernel[a] - 1) - 1) / stride[a] + 1;
        let (ho, wo) = (out_dim(0), out_dim(1));
        if ho < 1 || wo < 1 {
            return Err(Error::InvalidArgument(format!(
                "kernel {kernel:?} with padding {padding:?}, dilation {dilation:?} does not fit a {h}x{w} input"
            )));
        }
        check_float(offsets, "offsets")?;
        let taps = kh * kw;
        let batch = match offsets.size().as_slice() {
            [c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] => None,
            [b, c, oh, ow] if *c == 2 * taps && [*oh, *ow] == [ho, wo] => Some(*b),
            other => {
                return Err(Error::InvalidArgument(format!(
                    "offsets must be [{}, {ho}, {wo}] or [B, {}, {ho}, {wo}] for a {kh}x{kw} kernel on a {h}x{w} input, got {other:?}",
                    2 * taps,
                    2 * taps
                )))
            }
        };
        let off: Vec<f64> = Vec::<f64>::try_from(
            offsets.to_device(Device::Cpu).to_kind(Kind::Double).contiguous().view(-1),
        )?;
        let items = batch.unwrap_or(1);
        let plane = (ho * wo) as usize;
        let n = (items * taps) as usize * plane;
        let mut idx = [(); 4].map(|_| vec![0i64; n]);
        let mut wts = [(); 4].map(|_| vec![0f64; n]);
        let zero = h * w; // the extra zero element
        let mut s = 0usize;
        for item in 0..items as usize {
            // The zero element of item b sits at b * (H*W + 1) + H*W in the per-item layout.
            let base = if batch.is_some() { item as i64 * (h * w + 1) } else { 0 };
            for i in 0..kh {
                for j in 0..kw {
                    let k = (i * kw + j) as usize;
                    let off_y = &off[(item * 2 * taps as usize + 2 * k) * plane..][..plane];
                    let off_x = &off[(item * 2 * taps as usize + 2 * k + 1) * plane..][..plane];
                    for oy in 0..ho {
                        for ox in 0..wo {
                            let p = (oy * wo + ox) as usize;
                            let y = (oy * stride[0] - padding[0] + i * dilation[0]) as f64 + off_y[p];
                            let x = (ox * stride[1] - padding[1] + j * dilation[1]) as f64 + off_x[p];
                            let corners = bilinear(y, x, h, w);
                            for (c, (flat, wt)) in corners.into_iter().enumerate() {
                                idx[c][s] = base + flat.unwrap_or(zero);
                                wts[c][s] = wt;
                            }
                            s += 1;
                        }
                    }
                }
            }
        }
        let index = idx.map(|v| Tensor::from_slice(&v));
        let weight = wts.map(|v| Tensor::from_slice(&v).to_kind(kind));
        Ok(SamplingPlan {
            index,
            weight,
            input_size,
            output_size: [ho, wo],
            kernel,
            batch,
        })
    }

    /// The same plan with its tensors on `device`.
    pub fn to_device(&self, device: Device) -> Self {
        SamplingPlan {
            index: self.index.each_ref().map(|t| t.to_device(device)),
            weight: self.weight.each_ref().map(|t| t.to_device(device)),
            ..*self
        }
    }

    /// Another handle on the same tensors (no copy; libtorch reference counting).
    pub fn shallow_clone(&self) -> Self {
        SamplingPlan {
            index: self.index.each_ref().map(Tensor::shallow_clone),
            weight: self.weight.each_ref().map(Tensor::shallow_clone),
            ..*self
        }
    }

    /// Whether two plans hold the same tensor storage.
    pub fn shares_storage_with(&self, other: &SamplingPlan) -> bool {
        self.index[0].data_ptr() == other.index[0].data_ptr()
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
        self.index[0].device()
    }

    /// The column matrix of `input`: for each channel, tap and output pixel, the bilinear sample.
    ///
    /// # Shapes
    /// - `input`: `[B, C, H, W]`
    /// - output: `[B, C, K * H_out * W_out]` (tap-major within a channel, as torchvision's
    ///   `columns` and `weight.view(C_out, C_in * K)` expect)
    pub fn f_columns(&self, input: &Tensor) -> Result<Tensor> {
        check_float(input, "input")?;
        let (b, c, h, w) = input.size4().map_err(|_| {
            Error::InvalidArgument(format!("input must be [B, C, H, W], got {:?}", input.size()))
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
        let flat = input.reshape([b, c, h * w]);
        let zero = Tensor::f_zeros([b, c, 1], (input.kind(), input.device()))?;
        let padded = Tensor::f_cat(&[flat, zero], 2)?;
        let weight_kind = |t: &Tensor| t.to_kind(input.kind());
        let mut cols: Option<Tensor> = None;
        match self.batch {
            None => {
                for (idx, wt) in self.index.iter().zip(&self.weight) {
                    let term = padded.f_index_select(2, idx)?.f_mul(&weight_kind(wt))?;
                    cols = Some(match cols {
                        None => term,
                        Some(acc) => acc.f_add(&term)?,
                    });
                }
            }
            Some(_) => {
                // [C, B*(H*W+1)]: per-item indices already carry the item's base.
                let per_item = padded.permute([1, 0, 2]).reshape([c, b * (h * w + 1)]);
                for (idx, wt) in self.index.iter().zip(&self.weight) {
                    let n = idx.size()[0] / b;
                    let term = per_item
                        .f_index_select(1, idx)?
                        .view([c, b, n])
                        .permute([1, 0, 2])
                        .f_mul(&weight_kind(wt).view([b, 1, n]))?;
                    cols = Some(match cols {
                        None => term,
                        Some(acc) => acc.f_add(&term)?,
                    });
                }
            }
        }
        Ok(cols.expect("four corners"))
    }
}

/// torchvision's bilinear interpolation with zeros outside, as (flat index or `None` for an
/// out-of-range corner, weight) for the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1).
fn bilinear(y: f64, x: f64, h: i64, w: i64) -> [(Option<i64>, f64); 4] {
    if y <= -1.0 || y >= h as f64 || x <= -1.0 || x >= w as f64 || !y.is_finite() || !x.is_finite() {
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
        assert!(bilinear(-1.0, 0.0, 4, 4).iter().all(|(i, w)| i.is_none() && *w == 0.0));
        assert!(bilinear(0.0, 4.0, 4, 4).iter().all(|(i, _)| i.is_none()));
        // y in (-1, 0): the top corners fall outside, the bottom ones keep weight ly.
        let c = bilinear(-0.5, 1.0, 4, 4);
        assert_eq!(c[0].0, None);
        assert_eq!(c[2].0, Some(1));
        assert!((c[2].1 - 0.5).abs() < 1e-12);
    }
}
