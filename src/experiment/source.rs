//! Data sources named in experiment files, and the one place they are opened.
//!
//! An experiment names a source as a data set folder and a split
//! (`{ dataset = "data/synth/f195", split = "train" }`) or as the built-in toy task
//! (`{ toy = 64, split = "train" }`: 64 samples of [`crate::data::toy`], whose content depends on
//! the split name only). [`open_source`] turns a [`SourceRequest`] into a [`BatchSource`]: the
//! data module's [`Dataset`] loader for folders, checked against the experiment's camera;
//! runs take a [`SourceOpener`] so that tests and other front ends can serve their own sources
//! ([`DefaultOpener`] calls [`open_source`]).

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::camera::Camera;
use crate::camera::CameraModel;
use crate::data::format::Split;
use crate::data::loader::{Augment, Dataset, InputSize, LoaderConfig};
use crate::data::toy::{field_of_view_mask, toy_source};
use crate::data::BatchSource;
use crate::error::{Error, Result};
use crate::kernel::InputFrame;

/// A data source as an experiment names it (paths resolved).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SourceSpec {
    /// A data set folder (with `manifest.json`, see [`crate::data`]) and a split name; with a
    /// `fraction`, only that share of the split's samples, drawn with the run's seed
    /// ([`Dataset::keep_fraction`]).
    Dataset {
        path: PathBuf,
        split: String,
        #[serde(skip_serializing_if = "Option::is_none")]
        fraction: Option<f64>,
    },
    /// `samples` samples of the toy task; the split name seeds the content.
    Toy { samples: usize, split: String },
}

impl SourceSpec {
    /// A short description for logs and file metadata (`path:split` or `toy:split`).
    pub fn describe(&self) -> String {
        match self {
            SourceSpec::Dataset {
                path,
                split,
                fraction: None,
            } => format!("{}:{split}", path.display()),
            SourceSpec::Dataset {
                path,
                split,
                fraction: Some(f),
            } => format!("{}:{split} (fraction {f})", path.display()),
            SourceSpec::Toy { samples, split } => format!("toy({samples}):{split}"),
        }
    }

    /// The split name.
    pub fn split(&self) -> &str {
        match self {
            SourceSpec::Dataset { split, .. } | SourceSpec::Toy { split, .. } => split,
        }
    }
}

/// Everything needed to open a source for one use.
#[derive(Clone, Debug)]
pub struct SourceRequest<'a> {
    pub spec: &'a SourceSpec,
    pub batch_size: usize,
    /// `Some(seed)`: shuffle per epoch with this seed (training); `None`: storage order.
    pub shuffle: Option<u64>,
    /// The network input `[H, W]` every batch must have.
    pub input_size: [i64; 2],
    /// The camera and frame the network is built for (the toy task masks its field of view;
    /// a data set's camera must match it).
    pub camera: &'a Camera,
    pub frame: InputFrame,
    /// Augmentations (data sets only; the toy task has none).
    pub augment: Augment,
}

/// Opens sources for runs.
pub trait SourceOpener {
    /// A source for `req`; its input size must be `req.input_size`.
    fn open(&self, req: &SourceRequest<'_>) -> Result<Box<dyn BatchSource>>;
}

/// The opener of the command line: [`open_source`].
#[derive(Clone, Copy, Debug, Default)]
pub struct DefaultOpener;

impl SourceOpener for DefaultOpener {
    fn open(&self, req: &SourceRequest<'_>) -> Result<Box<dyn BatchSource>> {
        open_source(req)
    }
}

/// FNV-1a of a string: the toy task's content seed of a split name.
fn split_seed(split: &str) -> u64 {
    split.bytes().fold(0xCBF2_9CE4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01B3)
    })
}

/// Opens the source of `req` and checks that it serves `req.input_size`.
pub fn open_source(req: &SourceRequest<'_>) -> Result<Box<dyn BatchSource>> {
    let source: Box<dyn BatchSource> = match req.spec {
        SourceSpec::Toy { samples, split } => {
            let fov = field_of_view_mask(req.camera, &req.frame, req.input_size);
            Box::new(toy_source(
                *samples,
                req.input_size,
                split_seed(split),
                Some(&fov),
                req.batch_size,
                req.shuffle,
            )?)
        }
        SourceSpec::Dataset {
            path,
            split,
            fraction,
        } => open_dataset_folder(path, split, *fraction, req)?,
    };
    if source.input_size() != req.input_size {
        return Err(Error::Data {
            path: PathBuf::from(req.spec.describe()),
            message: format!(
                "serves {}x{} inputs, the experiment's network input is {}x{}",
                source.input_size()[0],
                source.input_size()[1],
                req.input_size[0],
                req.input_size[1]
            ),
        });
    }
    if source.is_empty() {
        return Err(Error::Data {
            path: PathBuf::from(req.spec.describe()),
            message: "has no samples".into(),
        });
    }
    Ok(source)
}

/// Largest disagreement, in network-input pixels, between where the experiment's camera and a
/// data set's camera put the same ray: the two must describe the same geometry, or calibrated
/// kernels would be computed for another lens than the images show. Rounding the stored size
/// moves nothing (intrinsics scale exactly); a different lens or resolution moves pixels by far
/// more than this.
pub const CAMERA_MATCH_TOL_PX: f64 = 0.5;

/// Where `camera`, seen through `frame` at a network input of `size` `[H, W]`, puts test rays
/// (on the axis, and at 15..75 degrees off it in four directions); `None` where it cannot.
fn probe_pixels(camera: &Camera, frame: &InputFrame, size: [i64; 2]) -> Vec<Option<[f64; 2]>> {
    let [w, h] = camera.size();
    let s = [
        size[1] as f64 / (w + frame.padding[0]) as f64,
        size[0] as f64 / (h + frame.padding[1]) as f64,
    ];
    let scaled = camera.rescaled(s, frame.convention);
    let mut out = vec![scaled.project([0.0, 0.0, 1.0])];
    for deg in [15.0f64, 30.0, 45.0, 60.0, 75.0] {
        for az in [0.0f64, 90.0, 180.0, 270.0] {
            let (t, a) = (deg.to_radians(), az.to_radians());
            let ray = [t.sin() * a.cos(), t.sin() * a.sin(), t.cos()];
            // Only rays both fields of view could hold are compared (a perspective camera
            // cannot see 75 degrees off axis).
            out.push(if t < camera.fov() / 2.0 {
                scaled.project(ray)
            } else {
                None
            });
        }
    }
    out
}

/// Checks that a data set's camera and frame give the experiment's geometry at `size`.
pub fn check_same_geometry(
    path: &Path,
    data_camera: &Camera,
    data_frame: &InputFrame,
    req: &SourceRequest<'_>,
) -> Result<()> {
    let a = probe_pixels(data_camera, data_frame, req.input_size);
    let b = probe_pixels(req.camera, &req.frame, req.input_size);
    let mut worst = 0.0f64;
    for (pa, pb) in a.iter().zip(&b) {
        if let (Some(pa), Some(pb)) = (pa, pb) {
            worst = worst.max((pa[0] - pb[0]).hypot(pa[1] - pb[1]));
        }
    }
    let centre = |p: &[Option<[f64; 2]>]| {
        p[0].map(|c| format!("({:.2}, {:.2})", c[0], c[1]))
            .unwrap_or_else(|| "none".into())
    };
    if worst > CAMERA_MATCH_TOL_PX {
        return Err(Error::Data {
            path: path.to_path_buf(),
            message: format!(
                "its camera ({}, stored {}x{}, padding {:?}) is not the experiment's input \
                 camera ({}, padding {:?}) at {}x{}: rays land up to {worst:.2} px apart \
                 (principal point {} vs {}); point [input] at the camera the data set was \
                 rendered with",
                data_camera.model_name(),
                data_camera.size()[0],
                data_camera.size()[1],
                data_frame.padding,
                req.camera.model_name(),
                req.frame.padding,
                req.input_size[0],
                req.input_size[1],
                centre(&a),
                centre(&b),
            ),
        });
    }
    Ok(())
}

/// Opens split `split` of the data set folder `path` (written by `calibconv synth`, see
/// [`crate::data::loader`]): batches of `req.batch_size`, shuffled per epoch with
/// `req.shuffle`'s seed (else in manifest order), padded right / bottom to `req.input_size`,
/// with `req.augment`; with a `fraction`, that share of the split drawn with `req.shuffle`'s
/// seed ([`Dataset::keep_fraction`]). The data set's camera must describe the same geometry as
/// the experiment's input camera ([`check_same_geometry`]).
pub fn open_dataset_folder(
    path: &Path,
    split: &str,
    fraction: Option<f64>,
    req: &SourceRequest<'_>,
) -> Result<Box<dyn BatchSource>> {
    let err = |message: String| Error::Data {
        path: path.to_path_buf(),
        message,
    };
    if !path.is_dir() {
        return Err(err(format!(
            "no such folder (split `{split}`); write the data sets with `calibconv synth`, or \
             use `{{ toy = N, split = \"{split}\" }}` for the built-in toy task"
        )));
    }
    if !path.join("manifest.json").is_file() {
        return Err(err(format!(
            "no manifest.json in {}: not a data set folder",
            path.display()
        )));
    }
    let split: Split = split.parse().map_err(err)?;
    let config = LoaderConfig {
        batch_size: req.batch_size,
        seed: req.shuffle.unwrap_or(0),
        shuffle: req.shuffle.is_some(),
        drop_last: false,
        input: InputSize::Exact([req.input_size[0] as usize, req.input_size[1] as usize]),
        augment: req.augment,
        prefetch: 2,
    };
    let mut data = Dataset::open(path, split, config)?;
    if let Some(f) = fraction {
        data = data.keep_fraction(f, req.shuffle.unwrap_or(0))?;
    }
    check_same_geometry(path, data.camera(), &data.input_frame(), req)?;
    Ok(Box::new(data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_that_are_not_data_sets_are_clear_errors() {
        let camera = crate::camera::shipped("pers");
        let dir = tempfile::tempdir().unwrap();
        let missing = SourceSpec::Dataset {
            path: dir.path().join("nope"),
            split: "train".into(),
            fraction: None,
        };
        let empty = SourceSpec::Dataset {
            path: dir.path().to_path_buf(),
            split: "train".into(),
            fraction: None,
        };
        let req = |spec| SourceRequest {
            spec,
            batch_size: 2,
            shuffle: None,
            input_size: [32, 32],
            camera: &camera,
            frame: InputFrame::default(),
            augment: Augment::default(),
        };
        let e = open_source(&req(&missing)).err().unwrap().to_string();
        assert!(e.contains("nope") && e.contains("no such folder"), "{e}");
        let e = open_source(&req(&empty)).err().unwrap().to_string();
        assert!(e.contains("no manifest.json in"), "{e}");
        let toy = SourceSpec::Toy {
            samples: 3,
            split: "val".into(),
        };
        let s = open_source(&req(&toy)).unwrap();
        assert_eq!((s.len(), s.input_size()), (3, [32, 32]));
    }
}
