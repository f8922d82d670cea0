//! TensorBoard event files through `tensorboard-rs`: scalars as `SPLIT/NAME` (e.g. `train/loss`,
//! `val/rmse`) and PNG images, readable by TensorBoard itself (a test reads them back with the
//! `tensorboard` Python package's `EventAccumulator`).
//!
//! `tensorboard-rs` 0.5's own image helper swaps width and height for non-square images, so
//! image summaries are built here from its protobuf types, with the PNG encoded by `image`.
//! Each writer creates a new `events.out.tfevents.*` file in its folder; a resumed run adds a
//! file next to the old one and TensorBoard merges them.

use std::path::{Path, PathBuf};

use image::RgbImage;
use protobuf::RepeatedField;
use tensorboard_proto::summary::{Summary, Summary_Image, Summary_Value};
use tensorboard_rs::summary_writer::FileWriter;

use crate::error::{Error, Result};
use crate::train::Reporter;

/// Writes one TensorBoard event file in a folder.
pub struct TensorBoard {
    dir: PathBuf,
    writer: FileWriter,
}

impl std::fmt::Debug for TensorBoard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TensorBoard")
            .field("dir", &self.dir)
            .finish()
    }
}

impl TensorBoard {
    /// A writer of a new event file in `dir` (created if needed). Fails with the folder's name
    /// if it cannot be created or written (`tensorboard-rs` would panic in its writer thread).
    pub fn create(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let probe = dir.join(format!(".write-probe-{}", std::process::id()));
        std::fs::write(&probe, b"").map_err(|e| Error::io(dir, e))?;
        let _ = std::fs::remove_file(&probe);
        Ok(TensorBoard {
            dir: dir.to_path_buf(),
            writer: FileWriter::new(dir),
        })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

/// An image summary: PNG bytes with the true width and height.
fn image_summary(tag: &str, img: &RgbImage) -> Result<Summary> {
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| Error::Image {
            path: PathBuf::from(tag),
            message: e.to_string(),
        })?;
    let mut image = Summary_Image::new();
    image.set_height(img.height() as i32);
    image.set_width(img.width() as i32);
    image.set_colorspace(3);
    image.set_encoded_image_string(png);
    let mut value = Summary_Value::new();
    value.set_tag(tag.to_string());
    value.set_image(image);
    let mut summary = Summary::new();
    summary.set_value(RepeatedField::from(vec![value]));
    Ok(summary)
}

impl Reporter for TensorBoard {
    fn scalars(&mut self, split: &str, step: u64, values: &[(String, f64)]) -> Result<()> {
        for (name, v) in values {
            self.writer.add_summary(
                tensorboard_rs::summary::scalar(&format!("{split}/{name}"), *v as f32),
                step as usize,
            );
        }
        Ok(())
    }

    fn image(&mut self, tag: &str, step: u64, image: &RgbImage) -> Result<()> {
        self.writer
            .add_summary(image_summary(tag, image)?, step as usize);
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        self.writer.flush();
        Ok(())
    }
}
