//! Data sources named in experiment files, and the one place they are opened.
//!
//! An experiment names a source as a data set folder and a split
//! (`{ dataset = "data/generated/f195", split = "train" }`) or as the built-in toy task
//! (`{ toy = 64, split = "train" }`: 64 samples of [`crate::data::toy`], whose content depends on
//! the split name only). [`open_source`] turns a [`SourceRequest`] into a
//! [`BatchSource`]; runs take a [`SourceOpener`] so that tests and other front ends can serve
//! their own sources ([`DefaultOpener`] calls [`open_source`]).

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::camera::Camera;
use crate::data::format::Split;
use crate::data::loader::{Augment, Dataset, InputSize, LoaderConfig};
use crate::data::toy::{field_of_view_mask, toy_source};
use crate::data::BatchSource;
use crate::error::{Error, Result};
use crate::kernel::InputFrame;

/// A data source as an experiment names it (paths resolved).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SourceSpec {
    /// A data set folder (with `manifest.json`, see [`crate::data`]) and a split name.
    Dataset { path: PathBuf, split: String },
    /// `samples` samples of the toy task; the split name seeds the content.
    Toy { samples: usize, split: String },
}

impl SourceSpec {
    /// A short description for logs and file metadata (`path:split` or `toy:split`).
    pub fn describe(&self) -> String {
        match self {
            SourceSpec::Dataset { path, split } => format!("{}:{split}", path.display()),
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
    /// The camera and frame the network is built for (the toy task masks its field of view).
    pub camera: &'a Camera,
    pub frame: InputFrame,
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
        SourceSpec::Dataset { path, split } => open_dataset_folder(path, split, req)?,
    };
    if source.input_size() != req.input_size {
        return Err(Error::Dataset {
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
        return Err(Error::Dataset {
            path: PathBuf::from(req.spec.describe()),
            message: "has no samples".into(),
        });
    }
    Ok(source)
}

/// Largest disagreement, in pixels, between the projections of the data set's camera and the
/// experiment's camera for the same ray before they count as different cameras. Both come from
/// the same file scaled the same way, so they agree to float rounding; 0.05 px still tells F165
/// from F195 at 16 px wide (they differ by 0.6 px at 80 deg there).
pub const CAMERA_MATCH_TOL_PX: f64 = 0.05;

/// Polar angles (degrees from the optical axis) of the rays [`cameras_match`] compares, at four
/// azimuths each; 80 deg is inside every camera of the paper (a pinhole projects it far outside
/// its image, which still compares).
const MATCH_ANGLES_DEG: [f64; 5] = [0.0, 20.0, 40.0, 60.0, 80.0];

/// Whether `a` and `b` are the same camera for the network: the same image size and the same
/// projection (within [`CAMERA_MATCH_TOL_PX`]) of rays at [`MATCH_ANGLES_DEG`] from the axis.
/// `Err` says how they differ.
pub fn cameras_match(a: &Camera, b: &Camera) -> std::result::Result<(), String> {
    use crate::camera::CameraModel;
    if a.size() != b.size() {
        return Err(format!(
            "image size {}x{} vs {}x{}",
            a.size()[0],
            a.size()[1],
            b.size()[0],
            b.size()[1]
        ));
    }
    for theta in MATCH_ANGLES_DEG {
        for k in 0..4 {
            let (t, phi) = (theta.to_radians(), k as f64 * std::f64::consts::FRAC_PI_2);
            let ray = [t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()];
            match (a.project(ray), b.project(ray)) {
                (None, None) => {}
                (Some(p), Some(q)) => {
                    let d = (p[0] - q[0]).hypot(p[1] - q[1]);
                    if d > CAMERA_MATCH_TOL_PX {
                        return Err(format!(
                            "a ray {theta} deg off axis lands {d:.2} px apart ({:.2}, {:.2}) vs \
                             ({:.2}, {:.2})",
                            p[0], p[1], q[0], q[1]
                        ));
                    }
                }
                _ => {
                    return Err(format!(
                        "a ray {theta} deg off axis is seen by one camera only"
                    ))
                }
            }
        }
    }
    Ok(())
}

/// Opens split `split` of the data set folder `path` (see the on-disk layout in
/// [`crate::data`]) with [`Dataset::open`]: batches of `req.batch_size`, shuffled per epoch
/// with `req.shuffle`, padded right / bottom to `req.input_size`, no augmentation.
///
/// The rule for cameras: the data set's `camera.toml` (the camera its images were rendered
/// with) must be the experiment's camera (`req.camera`: the `[input]` or `[[eval]]` camera,
/// scaled to `input.width` if given) up to [`CAMERA_MATCH_TOL_PX`], and its padding the
/// experiment's. This holds for standard kernels too: the network input size, the padding
/// mask and the radial bins (around the principal point) all come from the experiment's camera,
/// and calibrated kernels are only right for the camera of the images. An experiment that
/// evaluates a Pers-trained network on fisheye images names the fisheye camera in its
/// `[[eval]]`.
pub fn open_dataset_folder(
    path: &Path,
    split: &str,
    req: &SourceRequest<'_>,
) -> Result<Box<dyn BatchSource>> {
    let err = |message: String| Error::Dataset {
        path: path.to_path_buf(),
        message,
    };
    if !path.is_dir() {
        return Err(err(format!(
            "no such folder (split `{split}`); write a data set with `calibconv synth`, or use \
             `{{ toy = N, split = \"{split}\" }}` for the built-in toy task"
        )));
    }
    if !path.join("manifest.json").is_file() {
        return Err(err(format!(
            "no manifest.json in {}: not a data set folder",
            path.display()
        )));
    }
    let split_name: Split = split.parse().map_err(err)?;
    let [h, w] = req.input_size;
    let config = LoaderConfig {
        batch_size: req.batch_size,
        seed: req.shuffle.unwrap_or(0),
        shuffle: req.shuffle.is_some(),
        drop_last: false,
        input: InputSize::Exact([h.max(0) as usize, w.max(0) as usize]),
        augment: Augment::default(),
        prefetch: 2,
    };
    let dataset = Dataset::open(path, split_name, config)
        .map_err(|e| err(format!("split `{split}`: {e}")))?;
    cameras_match(dataset.camera(), req.camera).map_err(|why| {
        use crate::camera::CameraModel;
        err(format!(
            "its camera ({} {}x{}, camera.toml) is not the experiment's ({} {}x{}): {why}; point \
             the experiment's camera at the lens of this data set (and set `input.width` to its \
             image width)",
            dataset.camera().model_name(),
            dataset.camera().size()[0],
            dataset.camera().size()[1],
            req.camera.model_name(),
            req.camera.size()[0],
            req.camera.size()[1],
        ))
    })?;
    let padding = dataset.input_frame().padding;
    if padding != req.frame.padding {
        return Err(err(format!(
            "a {h}x{w} input pads its images by {padding:?} (right, bottom), the experiment \
             says {:?}",
            req.frame.padding
        )));
    }
    Ok(Box::new(dataset))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_that_are_not_data_sets_are_clear_errors() {
        let camera = crate::camera::load(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/data/cameras/pers.toml"
        ))
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let missing = SourceSpec::Dataset {
            path: dir.path().join("nope"),
            split: "train".into(),
        };
        let empty = SourceSpec::Dataset {
            path: dir.path().to_path_buf(),
            split: "train".into(),
        };
        let req = |spec| SourceRequest {
            spec,
            batch_size: 2,
            shuffle: None,
            input_size: [32, 32],
            camera: &camera,
            frame: InputFrame::default(),
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
