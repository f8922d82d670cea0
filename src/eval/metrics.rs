//! Evaluation metrics, accumulated over a whole evaluation set, overall and per radial bin.
//!
//! # Depth (the paper's Table 1, after Zioulis et al. 2018)
//!
//! Over valid pixels (`mask` true and ground truth `g > 0`), with prediction `d`:
//!
//! ```text
//! MRE      = mean(|d - g| / g)
//! MAE      = mean(|d - g|)
//! RMSE     = sqrt(mean((d - g)^2))
//! RMSE_log = sqrt(mean((ln d - ln g)^2))
//! delta_n  = fraction of pixels with max(d / g, g / d) < 1.25^n,  n = 1, 2, 3
//! ```
//!
//! Two conventions for "mean" ([`Averaging`]), both reported:
//!
//! - `per-image` (the authors' metrics code, github Sbrunoberenguel/DepthEstimationMetrics
//!   `metrics.py`, and the default of the report's Table 1): each metric per image over the
//!   image's valid pixels, then the mean over the images that have a valid pixel, so RMSE is
//!   the mean of per-image RMSEs;
//! - `pooled`: over every valid pixel of the set (sums accumulated in float64, one division at
//!   the end), so large images weigh by their pixel count and RMSE is the root of the set's
//!   mean square. Training validates with this one.
//!
//! Valid pixels are `mask && g > 0` (the authors: `g > 1e-7`; their RMSE_log also drops
//! `d <= 1e-7`, here the network's depth is positive by construction). A non-finite prediction
//! is not skipped: it makes the metrics non-finite, so it shows.
//!
//! # Segmentation (the paper's Table 2)
//!
//! One confusion matrix (rows: ground truth, columns: prediction) over the whole set, pixels with
//! a label in `0..classes` only (unknown / invalid pixels carry a negative label). Per class `c`:
//! `IoU_c = TP / (TP + FP + FN)`, `Acc_c = TP / (TP + FN)`; `mIoU` averages `IoU_c` over the
//! classes with `TP + FP + FN > 0`, `mAcc` averages `Acc_c` over classes present in the ground
//! truth; `pixel_acc = sum TP / sum (TP + FN)`. Values are fractions in `[0, 1]` (the paper prints
//! percentages).
//!
//! # Radial bins (the paper's Figures 4 and 6)
//!
//! Pixels are binned by the distance of their centre to the principal point, in network-input
//! pixels, into equal-width bins over `[0, r_max)`. Per bin: the pixel count, the metric pooled
//! over all the bin's pixels of the set, and the mean and standard deviation (population,
//! `ddof = 0`) over images of the per-image metric restricted to the bin (images with no valid
//! pixel in the bin do not count). Pixels at `r >= r_max` count in the totals only.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use tch::{Kind, Tensor};

use crate::error::{Error, Result};

/// Thresholds of `delta_1..3`: `1.25^n`.
pub const DELTA_THRESHOLDS: [f64; 3] = [1.25, 1.25 * 1.25, 1.25 * 1.25 * 1.25];

/// A named metric. Names are what files, TensorBoard tags and `val_metric` use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Metric {
    /// The training loss on the evaluation set (mean over valid pixels).
    Loss,
    /// Mean relative error `mean(|d - g| / g)`.
    Mre,
    /// Mean absolute error, metres.
    Mae,
    /// Root mean square error, metres.
    Rmse,
    /// Root mean square error of `ln d - ln g`.
    RmseLog,
    /// Fraction with `max(d/g, g/d) < 1.25`.
    Delta1,
    /// ... `< 1.25^2`.
    Delta2,
    /// ... `< 1.25^3`.
    Delta3,
    /// Mean intersection over union over classes.
    MIoU,
    /// Mean per-class accuracy.
    MAcc,
    /// Fraction of labelled pixels classified correctly.
    PixelAcc,
}

/// Depth metrics, in table order.
pub const DEPTH_METRICS: [Metric; 7] = [
    Metric::Mre,
    Metric::Mae,
    Metric::Rmse,
    Metric::RmseLog,
    Metric::Delta1,
    Metric::Delta2,
    Metric::Delta3,
];

/// Segmentation metrics, in table order.
pub const SEGMENTATION_METRICS: [Metric; 3] = [Metric::MIoU, Metric::MAcc, Metric::PixelAcc];

/// Every metric: the loss, then the depth and the segmentation metrics in table order.
pub const ALL_METRICS: [Metric; 11] = {
    let mut all = [Metric::Loss; 11];
    let mut i = 0;
    while i < DEPTH_METRICS.len() {
        all[1 + i] = DEPTH_METRICS[i];
        i += 1;
    }
    let mut j = 0;
    while j < SEGMENTATION_METRICS.len() {
        all[1 + DEPTH_METRICS.len() + j] = SEGMENTATION_METRICS[j];
        j += 1;
    }
    all
};

impl Metric {
    /// The name in files: `loss`, `mre`, `mae`, `rmse`, `rmse_log`, `delta1..3`, `miou`,
    /// `macc`, `pixel_acc`.
    pub fn name(self) -> &'static str {
        match self {
            Metric::Loss => "loss",
            Metric::Mre => "mre",
            Metric::Mae => "mae",
            Metric::Rmse => "rmse",
            Metric::RmseLog => "rmse_log",
            Metric::Delta1 => "delta1",
            Metric::Delta2 => "delta2",
            Metric::Delta3 => "delta3",
            Metric::MIoU => "miou",
            Metric::MAcc => "macc",
            Metric::PixelAcc => "pixel_acc",
        }
    }

    /// Whether a larger value is better (for choosing the best checkpoint).
    pub fn higher_is_better(self) -> bool {
        matches!(
            self,
            Metric::Delta1
                | Metric::Delta2
                | Metric::Delta3
                | Metric::MIoU
                | Metric::MAcc
                | Metric::PixelAcc
        )
    }

    /// Whether `a` is strictly better than `b` (a non-finite value is never better).
    pub fn is_better(self, a: f64, b: f64) -> bool {
        if !a.is_finite() {
            return false;
        }
        if !b.is_finite() {
            return true;
        }
        if self.higher_is_better() {
            a > b
        } else {
            a < b
        }
    }
}

impl Serialize for Metric {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Metric {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// How a depth metric is averaged over a set of images.
///
/// - `per-image` (the authors' convention, github Sbrunoberenguel/DepthEstimationMetrics
///   `metrics.py`): every metric per image over its valid pixels, then the mean over the images
///   (images without a valid pixel do not count). RMSE is the mean of per-image RMSEs.
/// - `pooled`: every valid pixel of the set in one mean, so an image weighs by its valid pixels
///   and RMSE is the root of the set's mean square.
///
/// Segmentation is neither: mIoU / mAcc come from one confusion matrix over the set whichever
/// averaging a table asks for.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Averaging {
    /// Per image, then the mean over images (the default of Table 1).
    #[default]
    PerImage,
    /// All valid pixels of the set pooled.
    Pooled,
}

impl Averaging {
    /// `per-image` or `pooled`.
    pub fn name(self) -> &'static str {
        match self {
            Averaging::PerImage => "per-image",
            Averaging::Pooled => "pooled",
        }
    }
}

impl fmt::Display for Averaging {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

// `FromStr`: "unknown averaging `x` (expected per-image or pooled)" for anything else.
calibconv_geometry::from_str_by_name!(Averaging, "averaging", {
    "per-image" => PerImage,
    "pooled" => Pooled,
});

impl fmt::Display for Metric {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Metric {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        ALL_METRICS
            .iter()
            .copied()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = ALL_METRICS.iter().map(|m| m.name()).collect();
                format!(
                    "unknown metric `{s}` (expected one of {})",
                    names.join(", ")
                )
            })
    }
}

/// Running mean and population standard deviation (Welford).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MeanStd {
    /// Values pushed.
    pub n: u64,
    mean: f64,
    m2: f64,
}

impl MeanStd {
    /// Adds one value.
    pub fn push(&mut self, x: f64) {
        self.n += 1;
        let d = x - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (x - self.mean);
    }
    /// The mean (NaN if empty).
    pub fn mean(&self) -> f64 {
        if self.n == 0 {
            f64::NAN
        } else {
            self.mean
        }
    }
    /// The population standard deviation (`ddof = 0`; NaN if empty).
    pub fn std(&self) -> f64 {
        if self.n == 0 {
            f64::NAN
        } else {
            (self.m2 / self.n as f64).sqrt()
        }
    }
}

/// Float64 sums of the depth errors over a set of valid pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DepthSums {
    /// Pixels.
    pub count: f64,
    /// Sums of `|d - g| / g`, `|d - g|`, `(d - g)^2` and `(ln d - ln g)^2`.
    pub abs_rel: f64,
    pub abs: f64,
    pub sq: f64,
    pub sq_log: f64,
    /// Pixels under each of [`DELTA_THRESHOLDS`].
    pub delta: [f64; 3],
}

impl DepthSums {
    fn from_row(v: &[f64]) -> Self {
        DepthSums {
            count: v[0],
            abs_rel: v[1],
            abs: v[2],
            sq: v[3],
            sq_log: v[4],
            delta: [v[5], v[6], v[7]],
        }
    }

    /// Adds `other` in.
    pub fn add(&mut self, o: &DepthSums) {
        self.count += o.count;
        self.abs_rel += o.abs_rel;
        self.abs += o.abs;
        self.sq += o.sq;
        self.sq_log += o.sq_log;
        for i in 0..3 {
            self.delta[i] += o.delta[i];
        }
    }

    /// The depth metrics in [`DEPTH_METRICS`] order (NaN if no pixel).
    pub fn metrics(&self) -> [f64; 7] {
        let n = self.count;
        if n == 0.0 {
            return [f64::NAN; 7];
        }
        [
            self.abs_rel / n,
            self.abs / n,
            (self.sq / n).sqrt(),
            (self.sq_log / n).sqrt(),
            self.delta[0] / n,
            self.delta[1] / n,
            self.delta[2] / n,
        ]
    }
}

fn to_f64s(t: &Tensor) -> Result<Vec<f64>> {
    Ok(Vec::<f64>::try_from(
        t.to_kind(Kind::Double).flatten(0, -1),
    )?)
}

/// Depth sums per group over valid pixels: entry `k` sums the pixels whose `group` is `k`.
///
/// # Shapes
/// - `pred`, `gt`: `[B, 1, H, W]` float (metres); `valid`: `[B, 1, H, W]` bool (pixels with
///   `gt <= 0` are dropped as well)
/// - `group`: `[B, 1, H, W]` int64 in `0..n_groups`
pub fn depth_sums(
    pred: &Tensor,
    gt: &Tensor,
    valid: &Tensor,
    group: &Tensor,
    n_groups: usize,
) -> Result<Vec<DepthSums>> {
    let valid = valid.logical_and(&gt.gt(0.0));
    let idx = group.f_masked_select(&valid)?;
    let d = pred.f_masked_select(&valid)?.to_kind(Kind::Double);
    let g = gt.f_masked_select(&valid)?.to_kind(Kind::Double);
    let diff = &d - &g;
    let abs = diff.abs();
    let ratio = (&d / &g).maximum(&(&g / &d));
    let qs = [
        abs.ones_like(),
        &abs / &g,
        abs.shallow_clone(),
        diff.square(),
        (d.log() - g.log()).square(),
        ratio.lt(DELTA_THRESHOLDS[0]).to_kind(Kind::Double),
        ratio.lt(DELTA_THRESHOLDS[1]).to_kind(Kind::Double),
        ratio.lt(DELTA_THRESHOLDS[2]).to_kind(Kind::Double),
    ];
    let rows: Vec<Tensor> = qs
        .iter()
        .map(|q| idx.f_bincount(Some(q), n_groups as i64))
        .collect::<std::result::Result<_, _>>()?;
    let flat = to_f64s(&Tensor::stack(&rows, 1))?; // [n_groups, 8]
    Ok(flat.chunks(8).map(DepthSums::from_row).collect())
}

/// Confusion matrices per group, `[n_groups][classes * classes]` (row-major, rows ground
/// truth), over pixels whose label is in `0..classes`.
///
/// # Shapes
/// - `pred`: `[B, H, W]` int64 predicted classes; `labels`: `[B, H, W]` int64
/// - `group`: `[B, H, W]` int64 in `0..n_groups`
pub fn confusions(
    pred: &Tensor,
    labels: &Tensor,
    group: &Tensor,
    classes: usize,
    n_groups: usize,
) -> Result<Vec<Vec<u64>>> {
    let c = classes as i64;
    let valid = labels.ge(0).logical_and(&labels.lt(c));
    let idx = (group.f_masked_select(&valid)? * c + labels.f_masked_select(&valid)?) * c
        + pred.f_masked_select(&valid)?.clamp(0, c - 1);
    let counts = idx.f_bincount::<Tensor>(None, (n_groups * classes * classes) as i64)?;
    let counts = Vec::<i64>::try_from(counts.to_kind(Kind::Int64))?;
    Ok(counts
        .chunks(classes * classes)
        .map(|ch| ch.iter().map(|&v| v as u64).collect())
        .collect())
}

/// Per-class and mean segmentation scores of a confusion matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct SegScores {
    /// `IoU_c` (`None`: class absent from ground truth and prediction).
    pub iou: Vec<Option<f64>>,
    /// `Acc_c` (`None`: class absent from ground truth).
    pub acc: Vec<Option<f64>>,
    /// Ground-truth pixels per class.
    pub support: Vec<u64>,
    /// The means ([`Metric::MIoU`], [`Metric::MAcc`], [`Metric::PixelAcc`]).
    pub miou: f64,
    pub macc: f64,
    pub pixel_acc: f64,
}

/// Per-class pixel counts of a confusion matrix: what mIoU, mAcc and pixel accuracy need, and
/// what adds up over images (the set's counts are the sums of its images' counts).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassCounts {
    /// Per class: true positives (the diagonal), ground-truth pixels (row sums) and predicted
    /// pixels (column sums).
    pub tp: Vec<u64>,
    pub gt: Vec<u64>,
    pub pred: Vec<u64>,
}

impl ClassCounts {
    /// Zero counts for `classes` classes.
    pub fn new(classes: usize) -> Self {
        ClassCounts {
            tp: vec![0; classes],
            gt: vec![0; classes],
            pred: vec![0; classes],
        }
    }

    /// The counts of a `classes x classes` confusion matrix (rows ground truth).
    pub fn from_confusion(cm: &[u64], classes: usize) -> Self {
        let mut c = ClassCounts::new(classes);
        for r in 0..classes {
            for k in 0..classes {
                let v = cm[r * classes + k];
                c.gt[r] += v;
                c.pred[k] += v;
                if r == k {
                    c.tp[r] += v;
                }
            }
        }
        c
    }

    /// Adds `o` in (same number of classes).
    pub fn add(&mut self, o: &ClassCounts) {
        for (a, b) in [
            (&mut self.tp, &o.tp),
            (&mut self.gt, &o.gt),
            (&mut self.pred, &o.pred),
        ] {
            for (x, y) in a.iter_mut().zip(b) {
                *x += *y;
            }
        }
    }

    /// Labelled pixels.
    pub fn pixels(&self) -> u64 {
        self.gt.iter().sum()
    }
}

impl SegScores {
    /// Scores of a `classes x classes` confusion matrix (rows ground truth).
    pub fn from_confusion(cm: &[u64], classes: usize) -> Self {
        SegScores::from_counts(&ClassCounts::from_confusion(cm, classes))
    }

    /// Scores of per-class counts (see [`ClassCounts`]).
    pub fn from_counts(counts: &ClassCounts) -> Self {
        let classes = counts.tp.len();
        let (mut iou, mut acc, mut support) = (Vec::new(), Vec::new(), Vec::new());
        let (mut tp_all, mut gt_all) = (0u64, 0u64);
        for c in 0..classes {
            let (tp, gt, pr) = (counts.tp[c], counts.gt[c], counts.pred[c]);
            let union = gt + pr - tp;
            iou.push((union > 0).then(|| tp as f64 / union as f64));
            acc.push((gt > 0).then(|| tp as f64 / gt as f64));
            support.push(gt);
            tp_all += tp;
            gt_all += gt;
        }
        let mean = |v: &[Option<f64>]| {
            let got: Vec<f64> = v.iter().flatten().copied().collect();
            if got.is_empty() {
                f64::NAN
            } else {
                got.iter().sum::<f64>() / got.len() as f64
            }
        };
        SegScores {
            miou: mean(&iou),
            macc: mean(&acc),
            pixel_acc: if gt_all > 0 {
                tp_all as f64 / gt_all as f64
            } else {
                f64::NAN
            },
            iou,
            acc,
            support,
        }
    }

    /// `[miou, macc, pixel_acc]` in [`SEGMENTATION_METRICS`] order.
    pub fn metrics(&self) -> [f64; 3] {
        [self.miou, self.macc, self.pixel_acc]
    }
}

/// Equal-width bins of the distance to the principal point.
#[derive(Clone, Debug, PartialEq)]
pub struct RadialBins {
    /// Principal point `[u, v]` in network-input pixels (column, row; pixel centres at
    /// integers).
    pub centre: [f64; 2],
    /// `n + 1` increasing edges from 0 to `r_max`.
    pub edges: Vec<f64>,
}

impl RadialBins {
    /// `n` bins over `[0, r_max)`; `r_max` defaults to the distance from `centre` to the
    /// farthest pixel centre of a `[H, W]` input (so that every pixel is in a bin).
    pub fn new(centre: [f64; 2], size: [i64; 2], n: usize, r_max: Option<f64>) -> Result<Self> {
        if n == 0 {
            return Err(Error::InvalidArgument(
                "radial bins: need at least one".into(),
            ));
        }
        let r_max = r_max.unwrap_or_else(|| {
            let (w, h) = ((size[1] - 1) as f64, (size[0] - 1) as f64);
            [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]
                .iter()
                .map(|p| (p[0] - centre[0]).hypot(p[1] - centre[1]))
                .fold(0.0, f64::max)
                // The farthest pixel itself lies at r_max: nudge so it is inside the last bin.
                * (1.0 + 1e-9)
                + 1e-9
        });
        if r_max.is_nan() || r_max <= 0.0 {
            return Err(Error::InvalidArgument(format!(
                "radial bins: r_max must be positive, got {r_max}"
            )));
        }
        let edges = (0..=n).map(|i| r_max * i as f64 / n as f64).collect();
        Ok(RadialBins { centre, edges })
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.edges.len() - 1
    }

    /// Whether there are no bins (never, by construction).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The bin of every pixel of a `[H, W]` input, `[H, W]` int64; pixels at `r >= r_max` get
    /// `len()` (the overflow bin).
    pub fn index_map(&self, size: [i64; 2]) -> Tensor {
        let n = self.len() as i64;
        let r_max = *self.edges.last().expect("edges");
        let opts = (Kind::Double, tch::Device::Cpu);
        let v = Tensor::arange(size[0], opts).view([-1, 1]) - self.centre[1];
        let u = Tensor::arange(size[1], opts).view([1, -1]) - self.centre[0];
        let r = (v.square() + u.square()).sqrt();
        let bin = (r * (n as f64 / r_max)).floor().to_kind(Kind::Int64);
        bin.clamp(0, n)
    }
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    #[test]
    fn averaging_names_round_trip_and_an_unknown_one_lists_them() {
        for a in [Averaging::PerImage, Averaging::Pooled] {
            assert_eq!(a.to_string().parse::<Averaging>(), Ok(a));
        }
        assert_eq!(
            "mean".parse::<Averaging>(),
            Err("unknown averaging `mean` (expected per-image or pooled)".to_string())
        );
    }

    /// Hand-computed values in float64 with a few operations: rounding only.
    const TOL: f64 = 1e-12;

    fn t(v: &[f64], shape: &[i64]) -> Tensor {
        Tensor::from_slice(v).view(shape).to_kind(Kind::Float)
    }

    #[test]
    fn depth_metrics_by_hand() {
        // One 2x2 image, prediction [[2, 1], [3, 9]], ground truth [[1, 2], [3, 5]], the fourth
        // pixel masked out. Valid (d, g): (2, 1), (1, 2), (3, 3).
        let pred = t(&[2.0, 1.0, 3.0, 9.0], &[1, 1, 2, 2]);
        let gt = t(&[1.0, 2.0, 3.0, 5.0], &[1, 1, 2, 2]);
        let mask = Tensor::from_slice(&[true, true, true, false]).view([1, 1, 2, 2]);
        let group = Tensor::zeros([1, 1, 2, 2], (Kind::Int64, Device::Cpu));
        let s = depth_sums(&pred, &gt, &mask, &group, 1).unwrap();
        let m = s[0].metrics();
        // MRE = (1/1 + 1/2 + 0) / 3 = 0.5
        // MAE = (1 + 1 + 0) / 3 = 2/3
        // RMSE = sqrt((1 + 1 + 0) / 3)
        // RMSE_log = sqrt((ln 2)^2 * 2 / 3)
        // ratios 2, 2, 1: delta1 = 1/3 (< 1.25), delta2 = 1/3 (< 1.5625), delta3 = 1/3 (< 1.953)
        let ln2 = 2f64.ln();
        let expected = [
            0.5,
            2.0 / 3.0,
            (2.0f64 / 3.0).sqrt(),
            (ln2 * ln2 * 2.0 / 3.0).sqrt(),
            1.0 / 3.0,
            1.0 / 3.0,
            1.0 / 3.0,
        ];
        for (i, (a, e)) in m.iter().zip(expected).enumerate() {
            assert!((a - e).abs() < TOL, "{}: {a} vs {e}", DEPTH_METRICS[i]);
        }
        // delta thresholds: a ratio of 1.5 passes delta2 and delta3 only; 1.9 delta3 only.
        let pred = t(&[1.5, 1.9], &[1, 1, 1, 2]);
        let gt = t(&[1.0, 1.0], &[1, 1, 1, 2]);
        let mask = pred.ones_like().to_kind(Kind::Bool);
        let group = Tensor::zeros([1, 1, 1, 2], (Kind::Int64, Device::Cpu));
        let m = depth_sums(&pred, &gt, &mask, &group, 1).unwrap()[0].metrics();
        assert_eq!(&m[4..], &[0.0, 0.5, 1.0]);
    }

    #[test]
    fn depth_sums_pool_pixels_across_images_not_per_image_means() {
        // Image 0: one pixel with error 2; image 1: three pixels with error 0.
        // Pooled RMSE = sqrt(4 / 4) = 1; the mean of per-image RMSEs would be (2 + 0) / 2 = 1
        // too, so use MAE: pooled 2 / 4 = 0.5, per-image mean (2 + 0) / 2 = 1.
        let pred = t(&[3.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0], &[2, 1, 2, 2]);
        let gt = t(&[1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0], &[2, 1, 2, 2]);
        let mask = gt.gt(0.0);
        let group = Tensor::from_slice(&[0i64, 0, 0, 0, 1, 1, 1, 1]).view([2, 1, 2, 2]);
        let s = depth_sums(&pred, &gt, &mask, &group, 2).unwrap();
        assert_eq!(s[0].count, 1.0);
        assert_eq!(s[1].count, 3.0);
        let mut total = DepthSums::default();
        s.iter().for_each(|x| total.add(x));
        assert!((total.metrics()[1] - 0.5).abs() < TOL);
    }

    #[test]
    fn confusion_and_scores_by_hand() {
        // 3 classes, labels -100 ignored. Pairs (gt, pred):
        // (0,0) (0,0) (0,1) (1,1) (1,2) (2,2) (-100, 0)
        let labels = Tensor::from_slice(&[0i64, 0, 0, 1, 1, 2, -100]).view([1, 1, 7]);
        let pred = Tensor::from_slice(&[0i64, 0, 1, 1, 2, 2, 0]).view([1, 1, 7]);
        let group = labels.zeros_like();
        let cm = confusions(&pred, &labels, &group, 3, 1).unwrap();
        assert_eq!(cm[0], [2, 1, 0, 0, 1, 1, 0, 0, 1]);
        let s = SegScores::from_confusion(&cm[0], 3);
        // IoU: c0 = 2 / (3 + 2 - 2) = 2/3; c1 = 1 / (2 + 2 - 1) = 1/3; c2 = 1 / (1 + 2 - 1) = 1/2
        // Acc: c0 = 2/3, c1 = 1/2, c2 = 1; pixel acc = 4/6.
        let miou = (2.0 / 3.0 + 1.0 / 3.0 + 0.5) / 3.0;
        let macc = (2.0 / 3.0 + 0.5 + 1.0) / 3.0;
        assert!((s.miou - miou).abs() < TOL);
        assert!((s.macc - macc).abs() < TOL);
        assert!((s.pixel_acc - 4.0 / 6.0).abs() < TOL);
        assert_eq!(s.support, [3, 2, 1]);

        // A class absent from both ground truth and prediction is left out of the means; one
        // that is only predicted counts with IoU 0 in mIoU and not in mAcc.
        let cm = [1, 1, 0, 0, 0, 0, 0, 0, 0];
        let s = SegScores::from_confusion(&cm, 3);
        assert_eq!(s.iou, [Some(0.5), Some(0.0), None]);
        assert_eq!(s.acc, [Some(0.5), None, None]);
        assert!((s.miou - 0.25).abs() < TOL);
        assert!((s.macc - 0.5).abs() < TOL);
    }

    #[test]
    fn mean_std_is_the_population_std() {
        let mut m = MeanStd::default();
        for x in [2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0] {
            m.push(x);
        }
        assert!((m.mean() - 5.0).abs() < TOL);
        assert!((m.std() - 2.0).abs() < TOL);
        assert!(MeanStd::default().mean().is_nan());
    }

    #[test]
    fn radial_bins_by_hand() {
        // Centre at pixel (u, v) = (1, 1) of a 3x4 image; r_max = 2 in 2 bins of width 1.
        let b = RadialBins::new([1.0, 1.0], [3, 4], 2, Some(2.0)).unwrap();
        let m = Vec::<i64>::try_from(b.index_map([3, 4]).flatten(0, -1)).unwrap();
        // distances row 0: sqrt2, 1, sqrt2, sqrt5 -> 1, 1, 1, overflow(2)
        // row 1: 1, 0, 1, 2 -> 1, 0, 1, 2;  row 2 = row 0
        assert_eq!(m, [1, 1, 1, 2, 1, 0, 1, 2, 1, 1, 1, 2]);
        // Default r_max covers every pixel: the farthest corner (3, 2) is in the last bin.
        let b = RadialBins::new([1.0, 1.0], [3, 4], 4, None).unwrap();
        let m = b.index_map([3, 4]);
        assert_eq!(m.max().int64_value(&[]), 3);
        assert!((b.edges[4] - 5f64.sqrt()).abs() < 1e-6);
    }

    #[test]
    fn metric_names_round_trip_and_directions() {
        for m in ALL_METRICS {
            assert_eq!(m.name().parse::<Metric>().unwrap(), m);
        }
        assert!("rsme".parse::<Metric>().is_err());
        assert!(Metric::Rmse.is_better(0.1, 0.2));
        assert!(Metric::MIoU.is_better(0.3, 0.2));
        assert!(!Metric::Rmse.is_better(f64::NAN, 0.2));
        assert!(Metric::Rmse.is_better(0.5, f64::NAN));
    }
}
