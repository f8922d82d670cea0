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

/// Opens split `split` of the data set folder `path` (see the on-disk layout in
/// [`crate::data`]).
///
/// The folder must exist and hold `manifest.json`. Reading the folder itself is the data
/// module's loader (batches of `req.batch_size`, shuffled with `req.shuffle`, resized and padded
/// to `req.input_size`), which is wired here; this build does not contain it yet, which is an
/// error naming the folder.
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
    let _ = req;
    Err(err(
        "this build has no data set folder loader yet (it comes with `calibconv::data`'s \
         loader); use `{ toy = N, split = ... }` sources meanwhile"
            .to_string(),
    ))
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
