//! What [`super::evaluate_with`] accumulates, written once for both tasks: a [`Task`] (depth or
//! segmentation) says how one batch turns into per-(image, radial bin) statistics and how
//! statistics turn into metrics; [`Pool`] sums them over the set, per image and per bin.

use image::RgbImage;
use tch::{Device, Kind, Tensor};

use super::metrics::{
    confusions, depth_sums, ClassCounts, DepthSums, MeanStd, Metric, SegScores, DEPTH_METRICS,
    SEGMENTATION_METRICS,
};
use super::record::{metric_map as record_map, SampleRecord};
use super::{visual, EvalOptions, RadialRow};
use crate::data::Batch;
use crate::error::Result;
use crate::loss::{depth_loss, segmentation_loss};

/// Metric values in a task's order.
type Metrics = Vec<(Metric, f64)>;

/// What one batch gave: its loss, the pixels it was taken over, the statistics of every
/// (image, group) pair (`groups` per image, image-major) and the prediction to picture.
pub(super) struct BatchStats<S> {
    pub loss: f64,
    pub valid: f64,
    pub sums: Vec<S>,
    pub shown: Tensor,
}

/// A batch and the network's prediction for it, with `group` (`[B, H, W]`, int64) the
/// (image, bin) index of each pixel in `0..n_groups`.
#[derive(Clone, Copy)]
pub(super) struct Predicted<'a> {
    pub out: &'a Tensor,
    pub batch: &'a Batch,
    pub group: &'a Tensor,
    pub n_groups: usize,
}

/// One task's side of the evaluation.
pub(super) trait Task {
    /// Additive statistics of a set of pixels.
    type Sums: Clone;
    /// The metrics [`Task::metrics`] returns, in order.
    const METRICS: &'static [Metric];
    /// Statistics of no pixels.
    fn empty(&self) -> Self::Sums;
    /// `into += s`.
    fn add(&self, into: &mut Self::Sums, s: &Self::Sums);
    /// Pixels counted in `s`.
    fn count(&self, s: &Self::Sums) -> u64;
    /// The metrics of `s` (pooled over its pixels).
    fn metrics(&self, s: &Self::Sums) -> Vec<f64>;
    /// The metrics of one image and its record.
    fn image(&self, id: &str, whole: &Self::Sums) -> (Vec<f64>, SampleRecord);
    /// Loss and statistics of a predicted batch.
    fn batch(&self, p: Predicted, opts: &EvalOptions) -> Result<BatchStats<Self::Sums>>;
    /// The picture of image `i` of `batch` (`shown` from [`Task::batch`]).
    fn panel(&self, batch: &Batch, shown: &Tensor, i: i64) -> Result<RgbImage>;
    /// Per-class scores of the whole set, for tasks that have classes.
    fn class_scores(&self, _total: &Self::Sums) -> Option<SegScores> {
        None
    }
}

/// Depth: sums of errors ([`DepthSums`]).
pub(super) struct DepthTask;

impl Task for DepthTask {
    type Sums = DepthSums;
    const METRICS: &'static [Metric] = &DEPTH_METRICS;
    fn empty(&self) -> DepthSums {
        DepthSums::default()
    }
    fn add(&self, into: &mut DepthSums, s: &DepthSums) {
        into.add(s);
    }
    fn count(&self, s: &DepthSums) -> u64 {
        s.count as u64
    }
    fn metrics(&self, s: &DepthSums) -> Vec<f64> {
        s.metrics().to_vec()
    }
    fn image(&self, id: &str, whole: &DepthSums) -> (Vec<f64>, SampleRecord) {
        let record = SampleRecord {
            id: id.to_string(),
            pixels: whole.count as u64,
            metrics: record_map(DEPTH_METRICS.iter().copied().zip(whole.metrics())),
            depth_sums: Some(*whole),
            class_counts: None,
        };
        (whole.metrics().to_vec(), record)
    }
    fn batch(&self, p: Predicted, opts: &EvalOptions) -> Result<BatchStats<DepthSums>> {
        let (out, batch, group, n_groups) = (p.out, p.batch, p.group, p.n_groups);
        let mask = batch.mask.to_device(opts.device);
        let gt = batch.depth.to_device(opts.device);
        let valid = mask.logical_and(&gt.gt(0.0));
        Ok(BatchStats {
            valid: valid.sum(Kind::Int64).int64_value(&[]) as f64,
            loss: depth_loss(out, &gt, &mask, opts.depth_loss)?.double_value(&[]),
            sums: depth_sums(out, &gt, &valid, &group.unsqueeze(1), n_groups)?,
            shown: out.shallow_clone(),
        })
    }
    fn panel(&self, batch: &Batch, shown: &Tensor, i: i64) -> Result<RgbImage> {
        visual::depth_panel(
            &batch.image.get(i),
            &batch.depth.get(i),
            &shown.get(i).to_device(Device::Cpu),
            &batch.mask.get(i),
        )
    }
}

/// Segmentation of `classes` classes: confusion matrices (row-major `classes x classes`).
pub(super) struct SegTask {
    pub classes: usize,
}

impl Task for SegTask {
    type Sums = Vec<u64>;
    const METRICS: &'static [Metric] = &SEGMENTATION_METRICS;
    fn empty(&self) -> Vec<u64> {
        vec![0; self.classes * self.classes]
    }
    fn add(&self, into: &mut Vec<u64>, s: &Vec<u64>) {
        for (x, y) in into.iter_mut().zip(s) {
            *x += *y;
        }
    }
    fn count(&self, s: &Vec<u64>) -> u64 {
        s.iter().sum()
    }
    fn metrics(&self, s: &Vec<u64>) -> Vec<f64> {
        SegScores::from_confusion(s, self.classes)
            .metrics()
            .to_vec()
    }
    fn image(&self, id: &str, whole: &Vec<u64>) -> (Vec<f64>, SampleRecord) {
        let counts = ClassCounts::from_confusion(whole, self.classes);
        let own = SegScores::from_counts(&counts).metrics();
        let record = SampleRecord {
            id: id.to_string(),
            pixels: self.count(whole),
            metrics: record_map(SEGMENTATION_METRICS.iter().copied().zip(own)),
            depth_sums: None,
            class_counts: Some(counts),
        };
        (own.to_vec(), record)
    }
    fn batch(&self, p: Predicted, opts: &EvalOptions) -> Result<BatchStats<Vec<u64>>> {
        let (out, batch, group, n_groups) = (p.out, p.batch, p.group, p.n_groups);
        let labels = batch.labels.to_device(opts.device);
        let c = self.classes;
        let valid = labels.ge(0).logical_and(&labels.lt(c as i64));
        let n_valid = valid.sum(Kind::Int64).int64_value(&[]) as f64;
        let loss = segmentation_loss(out, &labels)?.double_value(&[]);
        let pred = out.argmax(1, false);
        let sums = confusions(&pred, &labels, group, c, n_groups)?;
        Ok(BatchStats {
            loss,
            valid: n_valid,
            sums,
            shown: pred.to_device(Device::Cpu),
        })
    }
    fn panel(&self, batch: &Batch, shown: &Tensor, i: i64) -> Result<RgbImage> {
        visual::segmentation_panel(
            &batch.image.get(i),
            &batch.labels.get(i),
            &shown.get(i),
            &batch.mask.get(i),
        )
    }
    fn class_scores(&self, total: &Vec<u64>) -> Option<SegScores> {
        Some(SegScores::from_confusion(total, self.classes))
    }
}

/// A task's statistics over the set: pooled, per radial bin (pooled and over images), per
/// image.
pub(super) struct Pool<S> {
    pub total: S,
    pub bins: Vec<S>,
    pub bin_stats: Vec<Vec<MeanStd>>,
    pub image_stats: Vec<MeanStd>,
    pub bin_pixels: Vec<u64>,
    pub bin_images: Vec<u64>,
    pub pixels: u64,
    pub samples: Vec<SampleRecord>,
}

impl<S: Clone> Pool<S> {
    /// Empty statistics of `n_bins` bins.
    pub fn new<T: Task<Sums = S>>(task: &T, n_bins: usize) -> Self {
        let m = T::METRICS.len();
        Pool {
            total: task.empty(),
            bins: vec![task.empty(); n_bins],
            bin_stats: vec![vec![MeanStd::default(); m]; n_bins],
            image_stats: vec![MeanStd::default(); m],
            bin_pixels: vec![0; n_bins],
            bin_images: vec![0; n_bins],
            pixels: 0,
            samples: Vec::new(),
        }
    }

    /// Adds one image: its statistics per group (`n_bins` bins, then the overflow group).
    pub fn add_image<T: Task<Sums = S>>(&mut self, task: &T, id: &str, groups: &[S]) {
        let mut whole = task.empty();
        groups.iter().for_each(|s| task.add(&mut whole, s));
        task.add(&mut self.total, &whole);
        let n = task.count(&whole);
        self.pixels += n;
        let (own, record) = task.image(id, &whole);
        self.samples.push(record);
        if n > 0 {
            for (st, v) in self.image_stats.iter_mut().zip(own) {
                st.push(v);
            }
        }
        for (k, g) in groups.iter().take(self.bins.len()).enumerate() {
            let n = task.count(g);
            if n > 0 {
                task.add(&mut self.bins[k], g);
                self.bin_pixels[k] += n;
                self.bin_images[k] += 1;
                for (st, v) in self.bin_stats[k].iter_mut().zip(task.metrics(g)) {
                    st.push(v);
                }
            }
        }
    }

    /// The pooled metrics, the means over images and one row per radial bin.
    pub fn finish<T: Task<Sums = S>>(
        &self,
        task: &T,
        edges: &[f64],
    ) -> (Metrics, Metrics, Vec<RadialRow>) {
        let metrics = T::METRICS
            .iter()
            .copied()
            .zip(task.metrics(&self.total))
            .collect();
        let per_image = T::METRICS
            .iter()
            .zip(&self.image_stats)
            .map(|(m, s)| (*m, s.mean()))
            .collect();
        let radial = (0..self.bins.len())
            .map(|k| {
                let pooled = task.metrics(&self.bins[k]);
                let st = &self.bin_stats[k];
                RadialRow {
                    bin: k,
                    r_lo: edges[k],
                    r_hi: edges[k + 1],
                    pixels: self.bin_pixels[k],
                    images: self.bin_images[k],
                    values: T::METRICS
                        .iter()
                        .enumerate()
                        .map(|(i, m)| (*m, pooled[i], st[i].mean(), st[i].std()))
                        .collect(),
                }
            })
            .collect();
        (metrics, per_image, radial)
    }
}
