//! The files an evaluation writes, as types that the writer ([`super::Evaluation::write`]) and
//! the readers (the report, `evaluations.csv`) share:
//!
//! - `metrics.json`: [`MetricsRecord`]: the set's metrics, depth in both conventions
//!   ([`Averaging`]: `per-image`, the authors', and `pooled`), segmentation from one confusion
//!   matrix over the set, per-class scores and the radial bins;
//! - `per_image.json`: [`PerImageRecord`]: per test image (by sample id) the sums or class
//!   counts that the set's metrics are made of, so that a reader can recompute any metric over
//!   any multiset of images (the report's paired bootstrap over test images,
//!   [`PerImageRecord::aggregate`]).
//!
//! Non-finite values are written as `null` (`None`). A file that does not parse is an error
//! naming it; `metrics.json` files written before this format (no `format` field) are refused
//! with a hint to re-run the evaluation.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::metrics::{
    Averaging, ClassCounts, DepthSums, Metric, SegScores, DEPTH_METRICS, SEGMENTATION_METRICS,
};
use super::{class_names, Evaluation};
use crate::error::{Error, Result};
use crate::nn::Head;

/// File name of [`MetricsRecord`] in an evaluation folder.
pub const METRICS_FILE: &str = "metrics.json";
/// File name of [`PerImageRecord`] in an evaluation folder.
pub const PER_IMAGE_FILE: &str = "per_image.json";
/// `format` of `metrics.json`.
pub const METRICS_FORMAT: &str = "calibconv-metrics";
/// `format` of `per_image.json`.
pub const PER_IMAGE_FORMAT: &str = "calibconv-per-image";
/// Version of both formats (1 was the untyped `metrics.json` without `format`).
pub const VERSION: u32 = 2;

/// Metric values by metric; `None` where the value is not finite (or the set has no pixel).
pub type MetricMap = BTreeMap<Metric, Option<f64>>;

/// A map of the finite values of `pairs`.
pub fn metric_map(pairs: impl IntoIterator<Item = (Metric, f64)>) -> MetricMap {
    pairs
        .into_iter()
        .map(|(m, v)| (m, v.is_finite().then_some(v)))
        .collect()
}

/// Depth metrics in both conventions (see [`Averaging`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthVariants {
    /// Each metric per image over its valid pixels, then the mean over images.
    #[serde(rename = "per-image")]
    pub per_image: MetricMap,
    /// Each metric over all valid pixels of the set.
    pub pooled: MetricMap,
}

/// One class of the set's confusion matrix.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClassRecord {
    /// `None`: absent from ground truth and prediction.
    pub iou: Option<f64>,
    /// `None`: absent from ground truth.
    pub acc: Option<f64>,
    /// Ground-truth pixels.
    pub pixels: u64,
}

/// One radial bin (see [`super::RadialRow`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadialRecord {
    pub bin: usize,
    /// Distance range `[r_lo, r_hi)` to the principal point, network-input pixels.
    pub r_lo: f64,
    pub r_hi: f64,
    /// Valid pixels of the set in the bin; images with at least one.
    pub pixels: u64,
    pub images: u64,
    /// Each metric over all the bin's pixels of the set.
    pub pooled: MetricMap,
    /// Mean and population standard deviation over images of the metric restricted to the
    /// bin (depth: the per-image convention; segmentation: per-image confusion matrices).
    pub per_image_mean: MetricMap,
    pub per_image_std: MetricMap,
}

impl RadialRecord {
    /// The bin's value of `m` under `averaging` (segmentation: always the pooled confusion
    /// matrix of the bin, like the set's value).
    pub fn value(&self, m: Metric, averaging: Averaging, depth: bool) -> Option<f64> {
        let map = match (depth, averaging) {
            (true, Averaging::PerImage) => &self.per_image_mean,
            _ => &self.pooled,
        };
        map.get(&m).copied().flatten()
    }
}

/// What the caller of [`super::Evaluation::write`] says about the evaluation (the experiment
/// layer's `about`): the fields the report reads are typed; the rest is kept as written.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct About {
    /// The experiment (run) and the evaluation's name (`f195-calibrated`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub experiment: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub evaluation: Option<String>,
    /// `standard` or `calibrated`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kernel: Option<String>,
    /// The data set, described.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<String>,
    /// Every other field (camera file, input size, checkpoint, git revision, ...).
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

/// The fields both files open with: what the file is and the evaluation's task.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordHeader {
    /// [`METRICS_FORMAT`] or [`PER_IMAGE_FORMAT`], and [`VERSION`].
    pub format: String,
    pub version: u32,
    /// `depth` or `segmentation`.
    pub task: String,
}

impl RecordHeader {
    /// The header of a `format` file ([`VERSION`]) of an evaluation with `head`.
    fn new(format: &str, head: &Head) -> Self {
        RecordHeader {
            format: format.into(),
            version: VERSION,
            task: head.task_name().into(),
        }
    }

    /// Whether the file is of a depth evaluation.
    pub fn is_depth(&self) -> bool {
        self.task == "depth"
    }

    /// Refuses `path` unless it is a `want` file of [`VERSION`].
    fn check(&self, path: &Path, want: &str) -> Result<()> {
        let (format, version) = (&self.format, self.version);
        if format != want || version != VERSION {
            return Err(Error::Format {
                path: path.to_path_buf(),
                message: format!(
                    "format `{format}` version {version}, expected `{want}` version {VERSION}"
                ),
            });
        }
        Ok(())
    }
}

/// `metrics.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MetricsRecord {
    /// [`METRICS_FORMAT`].
    #[serde(flatten)]
    pub header: RecordHeader,
    /// Samples evaluated and valid (depth) / labelled (segmentation) pixels among them.
    pub images: u64,
    pub pixels: u64,
    /// Wall time of the evaluation.
    pub seconds: f64,
    /// The loss and the task's metrics as training validates with them (depth: `pooled`;
    /// segmentation: the set's confusion matrix), as `calibconv eval` prints them.
    pub metrics: MetricMap,
    /// Depth: both conventions ([`Averaging`]); the report's Table 1 uses `per-image` unless
    /// told otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<DepthVariants>,
    /// Segmentation: how mIoU / mAcc are averaged (one confusion matrix over the set; the
    /// per-image means are in `segmentation_per_image_mean` for reference only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segmentation_averaging: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segmentation_per_image_mean: Option<MetricMap>,
    /// Segmentation: per-class scores of the set's confusion matrix, by class name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub classes: Option<BTreeMap<String, ClassRecord>>,
    /// The radial bins, inner to outer.
    pub radial: Vec<RadialRecord>,
    /// The per-image file beside this one ([`PER_IMAGE_FILE`]).
    pub per_image_file: String,
    #[serde(flatten)]
    pub about: About,
}

/// What segmentation's `segmentation_averaging` says.
pub const SEGMENTATION_AVERAGING: &str = "one confusion matrix over the set";

impl MetricsRecord {
    /// Whether this is a depth evaluation.
    pub fn is_depth(&self) -> bool {
        self.header.is_depth()
    }

    /// The set's value of `m` under `averaging`: depth from [`DepthVariants`], segmentation
    /// and the loss from `metrics` (one value whatever the averaging).
    pub fn value(&self, m: Metric, averaging: Averaging) -> Option<f64> {
        if let (Some(d), true) = (&self.depth, DEPTH_METRICS.contains(&m)) {
            let map = match averaging {
                Averaging::PerImage => &d.per_image,
                Averaging::Pooled => &d.pooled,
            };
            return map.get(&m).copied().flatten();
        }
        self.metrics.get(&m).copied().flatten()
    }

    /// Reads and checks `path`.
    pub fn read(path: &Path) -> Result<Self> {
        let r: MetricsRecord = read_json(path)?;
        r.header.check(path, METRICS_FORMAT)?;
        Ok(r)
    }
}

/// One test image of `per_image.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleRecord {
    /// The data set's sample id (the same image has the same id under every kernel).
    pub id: String,
    /// Valid (depth) / labelled (segmentation) pixels of the image.
    pub pixels: u64,
    /// The image's own metrics (depth: over its valid pixels; segmentation: its own confusion
    /// matrix).
    pub metrics: MetricMap,
    /// Depth: the image's error sums (pooling adds these up).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_sums: Option<DepthSums>,
    /// Segmentation: the image's per-class counts (the set's confusion adds these up).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub class_counts: Option<ClassCounts>,
}

/// `per_image.json`: every evaluated image, in the source's order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PerImageRecord {
    /// [`PER_IMAGE_FORMAT`].
    #[serde(flatten)]
    pub header: RecordHeader,
    /// Segmentation: the class names, in count order; empty for depth.
    #[serde(default)]
    pub classes: Vec<String>,
    pub samples: Vec<SampleRecord>,
}

impl PerImageRecord {
    /// Reads and checks `path`.
    pub fn read(path: &Path) -> Result<Self> {
        let r: PerImageRecord = read_json(path)?;
        r.header.check(path, PER_IMAGE_FORMAT)?;
        let depth = r.header.is_depth();
        for s in &r.samples {
            let ok = if depth {
                s.depth_sums.is_some()
            } else {
                s.class_counts
                    .as_ref()
                    .is_some_and(|c| c.tp.len() == r.classes.len())
            };
            if !ok {
                return Err(Error::Format {
                    path: path.to_path_buf(),
                    message: format!("sample `{}`: no {} data", s.id, r.header.task),
                });
            }
        }
        Ok(r)
    }

    /// The metrics ([`DEPTH_METRICS`] or [`SEGMENTATION_METRICS`] order) of the multiset of
    /// samples `indices` (repeats count again: a bootstrap resample), as the set's metrics are
    /// computed: depth `per-image` = the mean over images with a valid pixel of each image's
    /// metric, depth `pooled` = the metrics of the summed sums, segmentation = the scores of
    /// the summed class counts (whatever `averaging`).
    pub fn aggregate(&self, indices: &[usize], averaging: Averaging) -> Vec<(Metric, f64)> {
        if self.header.is_depth() {
            let values = match averaging {
                Averaging::Pooled => {
                    let mut total = DepthSums::default();
                    for &i in indices {
                        if let Some(s) = &self.samples[i].depth_sums {
                            total.add(s);
                        }
                    }
                    total.metrics()
                }
                Averaging::PerImage => {
                    let (mut sum, mut n) = ([0.0; 7], 0usize);
                    for &i in indices {
                        if let Some(s) = self.samples[i].depth_sums.filter(|s| s.count > 0.0) {
                            for (a, v) in sum.iter_mut().zip(s.metrics()) {
                                *a += v;
                            }
                            n += 1;
                        }
                    }
                    sum.map(|a| if n == 0 { f64::NAN } else { a / n as f64 })
                }
            };
            DEPTH_METRICS.iter().copied().zip(values).collect()
        } else {
            let mut total = ClassCounts::new(self.classes.len());
            for &i in indices {
                if let Some(c) = &self.samples[i].class_counts {
                    total.add(c);
                }
            }
            let s = SegScores::from_counts(&total);
            SEGMENTATION_METRICS
                .iter()
                .copied()
                .zip(s.metrics())
                .collect()
        }
    }
}

impl Evaluation {
    /// The `metrics.json` record, with `about` (an object; its `experiment`, `evaluation`,
    /// `kernel` and `data` fields are typed, see [`About`]) merged in at the top level.
    pub fn record(&self, about: &serde_json::Value) -> Result<MetricsRecord> {
        let about: About = serde_json::from_value(about.clone())
            .map_err(|e| Error::InvalidArgument(format!("evaluation `about`: {e} (in {about})")))?;
        let depth = self.head == Head::Depth;
        let task_metrics = || {
            self.metrics
                .iter()
                .filter(|(m, _)| *m != Metric::Loss)
                .copied()
        };
        let classes = self.classes.as_ref().map(|c| {
            class_names(c.iou.len())
                .into_iter()
                .enumerate()
                .map(|(i, n)| {
                    let rec = ClassRecord {
                        iou: c.iou[i],
                        acc: c.acc[i],
                        pixels: c.support[i],
                    };
                    (n, rec)
                })
                .collect()
        });
        let radial = self
            .radial
            .iter()
            .map(|r| RadialRecord {
                bin: r.bin,
                r_lo: r.r_lo,
                r_hi: r.r_hi,
                pixels: r.pixels,
                images: r.images,
                pooled: metric_map(r.values.iter().map(|v| (v.0, v.1))),
                per_image_mean: metric_map(r.values.iter().map(|v| (v.0, v.2))),
                per_image_std: metric_map(r.values.iter().map(|v| (v.0, v.3))),
            })
            .collect();
        Ok(MetricsRecord {
            header: RecordHeader::new(METRICS_FORMAT, &self.head),
            images: self.images,
            pixels: self.pixels,
            seconds: self.seconds,
            metrics: metric_map(self.metrics.iter().copied()),
            depth: depth.then(|| DepthVariants {
                per_image: metric_map(self.per_image_mean.iter().copied()),
                pooled: metric_map(task_metrics()),
            }),
            segmentation_averaging: (!depth).then(|| SEGMENTATION_AVERAGING.to_string()),
            segmentation_per_image_mean: (!depth)
                .then(|| metric_map(self.per_image_mean.iter().copied())),
            classes,
            radial,
            per_image_file: PER_IMAGE_FILE.into(),
            about,
        })
    }

    /// The `per_image.json` record.
    pub fn per_image_record(&self) -> PerImageRecord {
        PerImageRecord {
            header: RecordHeader::new(PER_IMAGE_FORMAT, &self.head),
            classes: match self.head {
                Head::Segmentation { classes } => class_names(classes as usize),
                Head::Depth => Vec::new(),
            },
            samples: self.samples.clone(),
        }
    }
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| {
        let old = !text.contains("\"format\"");
        Error::Format {
            path: path.to_path_buf(),
            message: if old {
                format!(
                    "{e} (written before format version {VERSION}: run the evaluation again, \
                     `calibconv eval EXPERIMENT`)"
                )
            } else {
                e.to_string()
            },
        }
    })
}
