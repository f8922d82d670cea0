//! Training losses, on valid pixels only.
//!
//! - Depth: valid = `mask & (gt > 0)` (outside the fisheye image circle, padding and missing
//!   depth are masked out by the data). [`DepthLoss::L1`]: mean `|d - g|` in metres.
//!   [`DepthLoss::BerHu`] (reverse Huber, Laina et al. 2016): `|r|` for `|r| <= c`, else
//!   `(r^2 + c^2) / (2c)`, with `c = 0.2 max |r|` over the batch's valid pixels (not
//!   differentiated).
//! - Segmentation: cross-entropy over pixels whose label is in `0..classes`; unknown / invalid
//!   pixels carry `IGNORE_LABEL` (or any negative label) and are skipped, as PyTorch's
//!   `ignore_index`.
//!
//! A batch without a single valid pixel gives a loss of exactly 0 that still depends on the
//! prediction (so backward works and no NaN appears from 0 / 0).

use serde::{Deserialize, Serialize};
use tch::{Kind, Reduction, Tensor};

use crate::data::IGNORE_LABEL;
use crate::error::Result;

/// BerHu's threshold as a fraction of the largest absolute residual.
pub const BERHU_FRACTION: f64 = 0.2;

/// Depth regression losses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DepthLoss {
    /// Mean absolute error.
    #[default]
    L1,
    /// Reverse Huber.
    #[serde(rename = "berhu")]
    BerHu,
}

/// The depth loss over valid pixels.
///
/// # Shapes
/// - `pred`, `gt`: `[B, 1, H, W]` float (metres); `mask`: `[B, 1, H, W]` bool
/// - output: scalar
pub fn depth_loss(pred: &Tensor, gt: &Tensor, mask: &Tensor, kind: DepthLoss) -> Result<Tensor> {
    let valid = mask.logical_and(&gt.gt(0.0));
    let r = (pred - gt).f_masked_select(&valid)?;
    if r.numel() == 0 {
        return Ok(pred.sum(Kind::Float) * 0.0);
    }
    let a = r.abs();
    Ok(match kind {
        DepthLoss::L1 => a.mean(Kind::Float),
        DepthLoss::BerHu => {
            let c = (a.max().detach() * BERHU_FRACTION).clamp_min(1e-12);
            let quad = (r.square() + c.square()) / (&c * 2.0);
            a.where_self(&a.le_tensor(&c), &quad).mean(Kind::Float)
        }
    })
}

/// Cross-entropy over pixels with a label in `0..classes`.
///
/// # Shapes
/// - `logits`: `[B, classes, H, W]` float; `labels`: `[B, H, W]` int64
/// - output: scalar
pub fn segmentation_loss(logits: &Tensor, labels: &Tensor) -> Result<Tensor> {
    let classes = logits.size()[1];
    let valid = labels.ge(0).logical_and(&labels.lt(classes));
    if valid.any().int64_value(&[]) == 0 {
        return Ok(logits.sum(Kind::Float) * 0.0);
    }
    // Out-of-range labels become the ignore index too.
    let target = labels.where_scalarother(&valid, IGNORE_LABEL);
    Ok(logits.f_cross_entropy_loss::<Tensor>(&target, None, Reduction::Mean, IGNORE_LABEL, 0.0)?)
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    /// float32 arithmetic on a handful of values.
    const TOL: f64 = 1e-6;

    fn t(v: &[f32], shape: &[i64]) -> Tensor {
        Tensor::from_slice(v).view(shape)
    }

    #[test]
    fn depth_losses_by_hand() {
        let pred = t(&[2.0, 1.0, 3.0, 9.0], &[1, 1, 2, 2]);
        let gt = t(&[1.0, 3.0, 0.0, 5.0], &[1, 1, 2, 2]);
        let mask = Tensor::from_slice(&[true, true, true, false]).view([1, 1, 2, 2]);
        // Valid: residuals 1 and -2 (the third has no depth, the fourth is masked).
        let l1 = depth_loss(&pred, &gt, &mask, DepthLoss::L1).unwrap();
        assert!((l1.double_value(&[]) - 1.5).abs() < TOL);
        // c = 0.2 * 2 = 0.4: both beyond c: (1 + 0.16) / 0.8 = 1.45, (4 + 0.16) / 0.8 = 5.2.
        let b = depth_loss(&pred, &gt, &mask, DepthLoss::BerHu).unwrap();
        assert!((b.double_value(&[]) - (1.45 + 5.2) / 2.0).abs() < TOL);
        // Nothing valid: zero, and backward works.
        let p = pred.set_requires_grad(true);
        let z = depth_loss(&p, &gt, &mask.zeros_like(), DepthLoss::L1).unwrap();
        assert_eq!(z.double_value(&[]), 0.0);
        z.backward();
        assert!(p.grad().defined());
    }

    #[test]
    fn cross_entropy_skips_ignored_pixels() {
        // Two pixels, 2 classes: logits (0, 0) label 1 -> ln 2; logits (1, 0) label -100 skipped.
        let logits = t(&[0.0, 1.0, 0.0, 0.0], &[1, 2, 1, 2]);
        let labels = Tensor::from_slice(&[1i64, IGNORE_LABEL]).view([1, 1, 2]);
        let l = segmentation_loss(&logits, &labels).unwrap();
        assert!((l.double_value(&[]) - 2f64.ln()).abs() < TOL);
        let none = Tensor::full([1, 1, 2], IGNORE_LABEL, (Kind::Int64, Device::Cpu));
        assert_eq!(
            segmentation_loss(&logits, &none).unwrap().double_value(&[]),
            0.0
        );
    }
}
