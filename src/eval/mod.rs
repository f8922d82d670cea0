//! Evaluation: run a network over a [`BatchSource`] and accumulate the paper's metrics over the
//! whole set, overall and per radial bin (see [`metrics`] for the definitions), per test image,
//! plus a few prediction pictures. [`Evaluation::write`] writes `metrics.json` and
//! `per_image.json` (the typed records of [`record`]), `metrics.csv`, `radial.csv` and
//! `predictions/*.png`.
//!
//! The network runs in eval mode (BatchNorm running statistics) without gradients; batches are
//! moved to the requested device. Radial distances are measured in network-input pixels from
//! the principal point of the camera scaled to the input ([`principal_point`]).

mod accumulate;
pub mod metrics;
pub mod record;
pub mod visual;

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use image::RgbImage;
use tch::{Device, Kind, Tensor};

use crate::camera::{Camera, CameraModel};
use crate::data::BatchSource;
use crate::error::{Error, Result};
use crate::io::{write_bytes_atomic, write_png_atomic};
use crate::kernel::InputFrame;
use crate::loss::DepthLoss;
use crate::nn::{Head, UNet};
use crate::util::{fmt_f64, progress_bar};
use accumulate::{DepthTask, Pool, Predicted, SegTask, Task};
use metrics::{Metric, RadialBins, SegScores};
use record::{SampleRecord, METRICS_FILE, PER_IMAGE_FILE};

/// How to evaluate.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Radial bins (built for the input size, around the principal point).
    pub bins: RadialBins,
    /// Prediction pictures to keep: the first `panels` samples in the source's order.
    pub panels: usize,
    /// The loss reported as [`Metric::Loss`] (depth; segmentation uses cross-entropy).
    pub depth_loss: DepthLoss,
    pub device: Device,
    /// Show a progress bar on stderr.
    pub progress: bool,
}

/// One radial bin's results.
#[derive(Clone, Debug, PartialEq)]
pub struct RadialRow {
    /// Bin index and its distance range `[r_lo, r_hi)` in input pixels.
    pub bin: usize,
    pub r_lo: f64,
    pub r_hi: f64,
    /// Valid pixels of the set in the bin.
    pub pixels: u64,
    /// Images with at least one valid pixel in the bin.
    pub images: u64,
    /// Per metric: pooled over the bin's pixels, and mean and std over images.
    pub values: Vec<(Metric, f64, f64, f64)>,
}

/// The result of [`evaluate`].
#[derive(Clone, Debug)]
pub struct Evaluation {
    /// What the network predicts.
    pub head: Head,
    /// Samples evaluated and valid pixels among them.
    pub images: u64,
    pub pixels: u64,
    /// [`Metric::Loss`] then the task's metrics, pooled over the set.
    pub metrics: Vec<(Metric, f64)>,
    /// The task's metrics averaged over images (each image's own metric): depth's `per-image`
    /// convention ([`metrics::Averaging`]).
    pub per_image_mean: Vec<(Metric, f64)>,
    /// Every evaluated image, in the source's order.
    pub samples: Vec<SampleRecord>,
    /// Segmentation: per-class scores of the whole-set confusion matrix.
    pub classes: Option<SegScores>,
    pub radial: Vec<RadialRow>,
    /// `(sample id, picture)` for the first samples.
    pub panels: Vec<(String, RgbImage)>,
    /// Wall time of the evaluation.
    pub seconds: f64,
}

impl Evaluation {
    /// The value of `m`, if this task has it.
    pub fn metric(&self, m: Metric) -> Option<f64> {
        self.metrics.iter().find(|(k, _)| *k == m).map(|(_, v)| *v)
    }

    /// `metrics.json` ([`Evaluation::record`]), `per_image.json`
    /// ([`Evaluation::per_image_record`]), `metrics.csv` (a header of metric names and one
    /// row: the `metrics` of the record), `radial.csv`, and `predictions/<id>.png`, all written
    /// atomically into `dir`.
    pub fn write(&self, dir: &Path, about: &serde_json::Value) -> Result<()> {
        let record = serde_json::to_string_pretty(&self.record(about)?).expect("json");
        write_bytes_atomic(&dir.join(METRICS_FILE), record.as_bytes())?;
        // One line per sample: readable, and a tenth of the pretty size.
        let per_image = self.per_image_record();
        let mut text = format!(
            "{{\"format\": \"{}\", \"version\": {}, \"task\": \"{}\", \"classes\": {},\n\"samples\": [\n",
            per_image.header.format,
            per_image.header.version,
            per_image.header.task,
            serde_json::to_string(&per_image.classes).expect("json")
        );
        for (i, s) in per_image.samples.iter().enumerate() {
            text += &serde_json::to_string(s).expect("json");
            text += if i + 1 < per_image.samples.len() {
                ",\n"
            } else {
                "\n"
            };
        }
        text += "]}\n";
        write_bytes_atomic(&dir.join(PER_IMAGE_FILE), text.as_bytes())?;

        let header: Vec<&str> = self.metrics.iter().map(|(m, _)| m.name()).collect();
        let row: Vec<String> = self.metrics.iter().map(|(_, v)| fmt_f64(*v)).collect();
        let csv = format!(
            "images,pixels,{}\n{},{},{}\n",
            header.join(","),
            self.images,
            self.pixels,
            row.join(",")
        );
        write_bytes_atomic(&dir.join("metrics.csv"), csv.as_bytes())?;

        let mut radial = String::from("bin,r_lo,r_hi,pixels,images");
        if let Some(first) = self.radial.first() {
            for (m, ..) in &first.values {
                radial += &format!(",{m},{m}_mean,{m}_std");
            }
        }
        radial.push('\n');
        for r in &self.radial {
            radial += &format!(
                "{},{},{},{},{}",
                r.bin,
                fmt_f64(r.r_lo),
                fmt_f64(r.r_hi),
                r.pixels,
                r.images
            );
            for (_, pooled, mean, std) in &r.values {
                radial += &format!(",{},{},{}", fmt_f64(*pooled), fmt_f64(*mean), fmt_f64(*std));
            }
            radial.push('\n');
        }
        write_bytes_atomic(&dir.join("radial.csv"), radial.as_bytes())?;

        for (id, img) in &self.panels {
            let path = dir
                .join("predictions")
                .join(format!("{}.png", sanitize(id)));
            write_png_atomic(&path, img)?;
        }
        Ok(())
    }
}

/// The class names for `n` classes: the Stanford names if `n` matches, else `class0..`.
pub fn class_names(n: usize) -> Vec<String> {
    if n == crate::data::NUM_CLASSES {
        crate::data::CLASSES.iter().map(|s| s.to_string()).collect()
    } else {
        (0..n).map(|i| format!("class{i}")).collect()
    }
}

fn sanitize(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// The principal point `[u, v]` of `camera` in a network input of `input_size` `[H, W]` that is
/// the camera image padded by `frame.padding` and rescaled (the same scaling as the calibrated
/// offsets), or `None` if the camera cannot project its optical axis.
pub fn principal_point(
    camera: &Camera,
    frame: &InputFrame,
    input_size: [i64; 2],
) -> Option<[f64; 2]> {
    let [w, h] = camera.size();
    let s = [
        input_size[1] as f64 / (w + frame.padding[0]) as f64,
        input_size[0] as f64 / (h + frame.padding[1]) as f64,
    ];
    camera
        .rescaled(s, frame.convention)
        .project([0.0, 0.0, 1.0])
}

/// Evaluates `model` on every sample of `source` (epoch 0, in the source's order).
pub fn evaluate(model: &UNet, source: &dyn BatchSource, opts: &EvalOptions) -> Result<Evaluation> {
    let size = model.input_size();
    if source.input_size() != size {
        return Err(Error::InvalidArgument(format!(
            "the source serves {:?} inputs, the network is built for {size:?}",
            source.input_size()
        )));
    }
    evaluate_with(model.config().head, source, opts, |x| {
        model.f_forward_t(x, false)
    })
}

/// [`evaluate`] with any predictor: `predict` maps an image batch `[B, 3, H, W]` (on
/// `opts.device`) to depth `[B, 1, H, W]` or logits `[B, classes, H, W]` as `head` says.
pub fn evaluate_with(
    head: Head,
    source: &dyn BatchSource,
    opts: &EvalOptions,
    predict: impl Fn(&Tensor) -> Result<Tensor>,
) -> Result<Evaluation> {
    match head {
        Head::Depth => evaluate_task(&DepthTask, head, source, opts, predict),
        Head::Segmentation { classes } => {
            let task = SegTask {
                classes: classes as usize,
            };
            evaluate_task(&task, head, source, opts, predict)
        }
    }
}

/// [`evaluate_with`] for one task: every batch through `predict`, its statistics pooled per
/// image and radial bin, the loss weighted by valid pixels.
fn evaluate_task<T: Task>(
    task: &T,
    head: Head,
    source: &dyn BatchSource,
    opts: &EvalOptions,
    predict: impl Fn(&Tensor) -> Result<Tensor>,
) -> Result<Evaluation> {
    let start = Instant::now();
    let n_bins = opts.bins.len();
    let groups = n_bins + 1; // + overflow
    let bin_map = opts
        .bins
        .index_map(source.input_size())
        .to_device(opts.device);
    let mut pool = Pool::new(task, n_bins);
    let (mut images, mut loss_sum, mut loss_weight) = (0u64, 0.0f64, 0.0f64);
    let mut panels = Vec::new();
    let bar = progress_bar(source.len() as u64, "eval", opts.progress);
    let _guard = tch::no_grad_guard();
    for batch in source.batches(0, 0) {
        let batch = batch?;
        let b = batch.image.size()[0];
        let out = predict(&batch.image.to_device(opts.device))?;
        let group = (Tensor::arange(b, (Kind::Int64, opts.device)).view([-1, 1, 1])
            * groups as i64)
            + bin_map.unsqueeze(0);
        let predicted = Predicted {
            out: &out,
            batch: &batch,
            group: &group,
            n_groups: b as usize * groups,
        };
        let stats = task.batch(predicted, opts)?;
        if stats.valid > 0.0 {
            loss_sum += stats.loss * stats.valid;
            loss_weight += stats.valid;
        }
        for (i, img) in stats.sums.chunks(groups).enumerate() {
            pool.add_image(task, &batch.ids[i], img);
        }
        for i in 0..b {
            if panels.len() < opts.panels {
                let panel = task.panel(&batch, &stats.shown, i)?;
                panels.push((batch.ids[i as usize].clone(), panel));
            }
        }
        images += b as u64;
        bar.inc(b as u64);
    }
    bar.finish_and_clear();
    if images == 0 {
        return Err(Error::InvalidArgument(
            "the evaluation source has no samples".into(),
        ));
    }
    let loss = if loss_weight > 0.0 {
        loss_sum / loss_weight
    } else {
        f64::NAN
    };
    let (metrics, per_image_mean, radial) = pool.finish(task, &opts.bins.edges);
    let mut all = vec![(Metric::Loss, loss)];
    all.extend(metrics);
    Ok(Evaluation {
        head,
        images,
        pixels: pool.pixels,
        metrics: all,
        per_image_mean,
        classes: task.class_scores(&pool.total),
        radial,
        samples: pool.samples,
        panels,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The metrics of an evaluation as a name -> value map (for checkpoint metadata and logs).
pub fn metric_map(e: &Evaluation) -> BTreeMap<String, f64> {
    e.metrics
        .iter()
        .map(|(m, v)| (m.name().to_string(), *v))
        .collect()
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;
    use crate::data::memory::MemorySource;
    use metrics::Averaging;
    use record::{MetricsRecord, PerImageRecord};

    /// float64 sums of a few values: rounding only.
    const TOL: f64 = 1e-12;

    /// The evaluation of two 1x4 images (see the comment inside) that the tests below check
    /// by hand.
    fn two_images() -> Evaluation {
        // Two 1x4 images, ground truth 1 m everywhere; the predictor returns the image's first
        // channel: image 0 predicts [1, 2, 1, 1], image 1 predicts [1, 1, 1, 3] with its first
        // pixel masked out. Bins around (u, v) = (0, 0) of width 2: u = 0, 1 | u = 2, 3.
        let pred = Tensor::from_slice(&[1f32, 2., 1., 1., 1., 1., 1., 3.]).view([2, 1, 1, 4]);
        let image = pred.repeat([1, 3, 1, 1]);
        let mask = Tensor::from_slice(&[true, true, true, true, false, true, true, true])
            .view([2, 1, 1, 4]);
        let source = MemorySource::new(
            image,
            pred.ones_like(),
            Tensor::zeros([2, 1, 4], (Kind::Int64, Device::Cpu)),
            mask,
            vec!["a".into(), "b/c".into()],
            2,
            None,
        )
        .unwrap();
        let opts = EvalOptions {
            bins: RadialBins::new([0.0, 0.0], [1, 4], 2, Some(4.0)).unwrap(),
            panels: 1,
            depth_loss: DepthLoss::L1,
            device: Device::Cpu,
            progress: false,
        };
        evaluate_with(Head::Depth, &source, &opts, |x| Ok(x.narrow(1, 0, 1))).unwrap()
    }

    /// [`two_images`] written to a temporary folder, and its `metrics.json`.
    fn two_images_written() -> (tempfile::TempDir, MetricsRecord) {
        let dir = tempfile::tempdir().unwrap();
        two_images()
            .write(dir.path(), &json!({"evaluation": "unit"}))
            .unwrap();
        let rec = MetricsRecord::read(&dir.path().join("metrics.json")).unwrap();
        (dir, rec)
    }

    #[test]
    fn pooled_per_image_and_radial_values_by_hand() {
        let e = two_images();
        assert_eq!((e.images, e.pixels), (2, 7));
        // Errors: image 0 [0, 1, 0, 0], image 1 [-, 0, 0, 2]. Pooled MAE 3/7; L1 loss the same.
        assert!((e.metric(Metric::Mae).unwrap() - 3.0 / 7.0).abs() < TOL);
        assert!((e.metric(Metric::Loss).unwrap() - 3.0 / 7.0).abs() < 1e-7);
        // Per-image MAE 1/4 and 2/3.
        let pim = e
            .per_image_mean
            .iter()
            .find(|(m, _)| *m == Metric::Mae)
            .unwrap()
            .1;
        assert!((pim - (0.25 + 2.0 / 3.0) / 2.0).abs() < TOL);
        // Bin 0: pixels 2 + 1, pooled 1/3, per image 1/2 and 0 -> mean 1/4, std 1/4.
        // Bin 1: pixels 2 + 2, pooled 2/4, per image 0 and 1 -> mean 1/2, std 1/2.
        let mae = |r: &RadialRow| *r.values.iter().find(|v| v.0 == Metric::Mae).unwrap();
        let (r0, r1) = (&e.radial[0], &e.radial[1]);
        assert_eq!((r0.pixels, r0.images, r1.pixels, r1.images), (3, 2, 4, 2));
        let (_, p, m, s) = mae(r0);
        assert!((p - 1.0 / 3.0).abs() < TOL && (m - 0.25).abs() < TOL && (s - 0.25).abs() < TOL);
        let (_, p, m, s) = mae(r1);
        assert!((p - 0.5).abs() < TOL && (m - 0.5).abs() < TOL && (s - 0.5).abs() < TOL);
        assert_eq!(e.panels.len(), 1);
    }

    #[test]
    fn written_files_hold_both_depth_conventions_by_hand() {
        let (dir, rec) = two_images_written();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        assert!(
            csv.starts_with("images,pixels,loss,mre,mae,rmse,rmse_log,delta1,delta2,delta3\n2,7,")
        );
        let radial = std::fs::read_to_string(dir.path().join("radial.csv")).unwrap();
        assert!(
            radial.starts_with("bin,r_lo,r_hi,pixels,images,mre,mre_mean,mre_std,"),
            "{radial}"
        );
        assert_eq!(radial.lines().count(), 3);
        assert_eq!(rec.about.evaluation.as_deref(), Some("unit"));
        assert!(dir.path().join("predictions/a.png").exists());

        // Both depth conventions, by hand. Image 0: errors [0, 1, 0, 0]; image 1 (3 valid):
        // [0, 0, 2]. Per image RMSE sqrt(1/4) = 1/2 and sqrt(4/3); delta1 (ratios 1, 2, 1, 1
        // and 1, 1, 3) 3/4 and 2/3. Per-image: the means of those; pooled: over the 7 pixels.
        let per_image_rmse = (0.5 + (4.0f64 / 3.0).sqrt()) / 2.0;
        let cases = [
            (Metric::Rmse, Averaging::PerImage, per_image_rmse),
            (Metric::Rmse, Averaging::Pooled, (5.0f64 / 7.0).sqrt()),
            (
                Metric::Delta1,
                Averaging::PerImage,
                (0.75 + 2.0 / 3.0) / 2.0,
            ),
            (Metric::Delta1, Averaging::Pooled, 5.0 / 7.0),
            (Metric::Mae, Averaging::PerImage, (0.25 + 2.0 / 3.0) / 2.0),
            (Metric::Mae, Averaging::Pooled, 3.0 / 7.0),
        ];
        for (m, a, want) in cases {
            let got = rec.value(m, a).unwrap();
            assert!((got - want).abs() < TOL, "{m} {a}: {got} vs {want}");
        }
        // `metrics` keeps what training validates with: pooled.
        assert_eq!(
            rec.metrics[&Metric::Rmse],
            rec.depth.as_ref().unwrap().pooled[&Metric::Rmse]
        );
        assert_eq!(rec.radial.len(), 2);
        assert_eq!(rec.radial[1].per_image_mean[&Metric::Mae], Some(0.5));
    }

    #[test]
    fn per_image_json_reaggregates_to_the_set_values() {
        let (dir, rec) = two_images_written();
        // per_image.json: both images by id; re-aggregating all of them gives the set's
        // values, and a resample with image 0 twice gives image 0's own.
        let per = PerImageRecord::read(&dir.path().join("per_image.json")).unwrap();
        let ids: Vec<&str> = per.samples.iter().map(|s| s.id.as_str()).collect();
        assert_eq!(ids, ["a", "b/c"]);
        assert_eq!(per.samples[1].pixels, 3);
        let rmse1 = per.samples[1].metrics[&Metric::Rmse].unwrap();
        assert!((rmse1 - (4.0f64 / 3.0).sqrt()).abs() < TOL);
        for a in [Averaging::PerImage, Averaging::Pooled] {
            for (m, v) in per.aggregate(&[0, 1], a) {
                let want = rec.value(m, a).unwrap();
                assert!((v - want).abs() < TOL, "{m} {a}: {v} vs {want}");
            }
            let rmse = per.aggregate(&[0, 0], a)[2];
            assert_eq!(rmse.0, Metric::Rmse);
            assert!((rmse.1 - 0.5).abs() < TOL);
        }
    }

    #[test]
    fn old_metrics_json_is_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.json");
        std::fs::write(&path, r#"{"task": "depth", "metrics": {"rmse": 1.0}}"#).unwrap();
        let e = MetricsRecord::read(&path).unwrap_err().to_string();
        assert!(
            e.contains("metrics.json") && e.contains("run the evaluation again"),
            "{e}"
        );
        let e = MetricsRecord::read(&dir.path().join("none.json")).unwrap_err();
        assert!(e.to_string().contains("none.json"), "{e}");
    }

    #[test]
    fn segmentation_uses_one_confusion_matrix_over_the_set() {
        // Two 1x2 images, 2 classes. Image 0: gt [0, 1] pred [0, 0]; image 1: gt [1, 1] pred
        // [1, 1]. Whole set: TP0 = 1, FP0 = 1, TP1 = 2, FN1 = 1 -> IoU0 = 1/2, IoU1 = 2/3.
        // (The mean of per-image mIoUs would be (1/2 * (1/2 + 0) + 1) / 2 = 5/8 instead.)
        let logits = Tensor::from_slice(&[1f32, 1., 0., 0., 0., 0., 1., 1.]).view([2, 2, 1, 2]);
        let image = Tensor::zeros([2, 3, 1, 2], (Kind::Float, Device::Cpu));
        let source = MemorySource::new(
            image,
            Tensor::ones([2, 1, 1, 2], (Kind::Float, Device::Cpu)),
            Tensor::from_slice(&[0i64, 1, 1, 1]).view([2, 1, 2]),
            Tensor::ones([2, 1, 1, 2], (Kind::Bool, Device::Cpu)),
            vec!["a".into(), "b".into()],
            1,
            None,
        )
        .unwrap();
        let opts = EvalOptions {
            bins: RadialBins::new([0.0, 0.0], [1, 2], 1, None).unwrap(),
            panels: 0,
            depth_loss: DepthLoss::L1,
            device: Device::Cpu,
            progress: false,
        };
        let calls = std::cell::Cell::new(0);
        let e = evaluate_with(Head::Segmentation { classes: 2 }, &source, &opts, |_| {
            let i = calls.get();
            calls.set(i + 1);
            Ok(logits.narrow(0, i, 1))
        })
        .unwrap();
        assert!((e.metric(Metric::MIoU).unwrap() - (0.5 + 2.0 / 3.0) / 2.0).abs() < TOL);
        // mAcc: class 0 1/1, class 1 2/3.
        assert!((e.metric(Metric::MAcc).unwrap() - (1.0 + 2.0 / 3.0) / 2.0).abs() < TOL);
        assert!((e.metric(Metric::PixelAcc).unwrap() - 0.75).abs() < TOL);
        assert_eq!(e.classes.as_ref().unwrap().support, [1, 3]);
        // Per image: the class counts; summed over both images they give the set's scores.
        let per = e.per_image_record();
        let c0 = per.samples[0].class_counts.as_ref().unwrap();
        assert_eq!(
            (&c0.tp, &c0.gt, &c0.pred),
            (&vec![1, 0], &vec![1, 1], &vec![2, 0])
        );
        let all = per.aggregate(&[0, 1], Averaging::PerImage);
        assert!((all[0].1 - (0.5 + 2.0 / 3.0) / 2.0).abs() < TOL);
        // Image 1 twice: gt [1, 1] pred [1, 1] twice -> class 1 only, IoU 1.
        assert_eq!(per.aggregate(&[1, 1], Averaging::Pooled)[0].1, 1.0);
        let rec = e.record(&json!({})).unwrap();
        assert_eq!(
            rec.segmentation_averaging.as_deref(),
            Some("one confusion matrix over the set")
        );
        assert!(rec.depth.is_none());
        assert_eq!(rec.classes.unwrap()["class1"].pixels, 3);
    }
}
