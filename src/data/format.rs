//! The on-disk data set: PNG encodings of the sample files, colourised previews, and the
//! manifest (layout in the [`crate::data`] module docs).
//!
//! Encodings (all PNG, `width x height` of the stored camera):
//! - `rgb/ID.png`: 8-bit RGB;
//! - `depth/ID.png`: 16-bit grey, `metres = value * depth_scale` (the manifest's
//!   `depth_scale`, [`DEPTH_SCALE`] = 1 mm by default, so at most 65.535 m); `0` = missing.
//!   A depth beyond the range is stored as missing (and its mask is false), never clamped;
//! - `labels/ID.png`: 8-bit grey, class id in `CLASSES` order, [`UNKNOWN_PNG_LABEL`] = unknown;
//! - `mask/ID.png`: 8-bit grey, 255 = valid (inside the image and depth present), 0 otherwise;
//! - `previews/ID.png`: `3 width x height` RGB: the image | depth colourised from 0 (dark blue)
//!   to [`PREVIEW_MAX_DEPTH_M`] (yellow) | labels in [`CLASS_COLOURS`]; black where invalid.
//!
//! Readers check the colour type, the size against the manifest, and the value ranges, and name
//! the file in every error.

use std::path::{Path, PathBuf};

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ExtendedColorType, ImageEncoder};
use serde::{Deserialize, Serialize};

use crate::data::views::View;
use crate::data::{CLASSES, NUM_CLASSES, UNKNOWN_PNG_LABEL};
use crate::error::{Error, Result};

/// Default metres per unit of the 16-bit depth PNGs (1 mm; range 65.535 m).
pub const DEPTH_SCALE: f64 = 1e-3;

/// Depth mapped to the top of the preview colour scale, in metres.
pub const PREVIEW_MAX_DEPTH_M: f32 = 8.0;

/// Preview colour of each class, in `CLASSES` order.
pub const CLASS_COLOURS: [[u8; 3]; NUM_CLASSES] = [
    [255, 127, 14],  // beam
    [188, 189, 34],  // board
    [140, 86, 75],   // bookcase
    [174, 199, 232], // ceiling
    [214, 39, 40],   // chair
    [127, 127, 127], // clutter
    [148, 103, 189], // column
    [44, 160, 44],   // door
    [152, 223, 138], // floor
    [227, 119, 194], // sofa
    [255, 187, 120], // table
    [31, 119, 180],  // wall
    [23, 190, 207],  // window
];

/// The sub-folders of a data set, one file per sample in each.
pub const SAMPLE_DIRS: [&str; 5] = ["rgb", "depth", "labels", "mask", "previews"];

/// Path of sample `id` in sub-folder `dir` of the data set at `root`.
pub fn sample_path(root: &Path, dir: &str, id: &str) -> PathBuf {
    root.join(dir).join(format!("{id}.png"))
}

fn encode(width: usize, height: usize, bytes: &[u8], colour: ExtendedColorType) -> Vec<u8> {
    let mut out = Vec::new();
    // Fixed compression and filter settings: the same pixels always give the same bytes.
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(bytes, width as u32, height as u32, colour)
        .expect("PNG encoding into memory cannot fail for a matching buffer");
    out
}

/// The five PNG files of one sample, encoded (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct EncodedSample {
    /// `rgb/ID.png`.
    pub rgb: Vec<u8>,
    /// `depth/ID.png`.
    pub depth: Vec<u8>,
    /// `labels/ID.png`.
    pub labels: Vec<u8>,
    /// `mask/ID.png`.
    pub mask: Vec<u8>,
    /// `previews/ID.png`.
    pub preview: Vec<u8>,
}

impl EncodedSample {
    /// The files in [`SAMPLE_DIRS`] order.
    pub fn files(&self) -> [&[u8]; 5] {
        [
            &self.rgb,
            &self.depth,
            &self.labels,
            &self.mask,
            &self.preview,
        ]
    }
}

/// Depth in metres to PNG units: `round(d / scale)`, 0 for missing, non-finite or beyond
/// 65535 units.
pub fn depth_units(d: f32, scale: f64) -> u16 {
    if !(d.is_finite() && d > 0.0) {
        return 0;
    }
    let v = (d as f64 / scale).round();
    if v >= 1.0 && v <= u16::MAX as f64 {
        v as u16
    } else {
        0
    }
}

/// Encodes a view. The stored mask is the view's mask and a representable depth.
pub fn encode_sample(view: &View, depth_scale: f64) -> EncodedSample {
    let (w, h) = (view.width, view.height);
    let units: Vec<u16> = view
        .depth
        .iter()
        .map(|&d| depth_units(d, depth_scale))
        .collect();
    let mask: Vec<bool> = (0..w * h).map(|i| view.mask[i] && units[i] > 0).collect();
    let rgb: Vec<u8> = view.rgb.iter().flatten().copied().collect();
    let depth_bytes: Vec<u8> = units.iter().flat_map(|u| u.to_ne_bytes()).collect();
    let mask_bytes: Vec<u8> = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    EncodedSample {
        rgb: encode(w, h, &rgb, ExtendedColorType::Rgb8),
        depth: encode(w, h, &depth_bytes, ExtendedColorType::L16),
        labels: encode(w, h, &view.labels, ExtendedColorType::L8),
        mask: encode(w, h, &mask_bytes, ExtendedColorType::L8),
        preview: encode(
            3 * w,
            h,
            &preview_pixels(view, &mask),
            ExtendedColorType::Rgb8,
        ),
    }
}

/// A dark-blue -> teal -> yellow colour scale for `x` in `[0, 1]`.
pub fn depth_colour(x: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [20.0, 20.0, 90.0],
        [40.0, 90.0, 160.0],
        [30.0, 160.0, 140.0],
        [140.0, 200.0, 70.0],
        [250.0, 230.0, 40.0],
    ];
    let x = x.clamp(0.0, 1.0) * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let w = x - i as f32;
    [0, 1, 2].map(|k| (STOPS[i][k] * (1.0 - w) + STOPS[i + 1][k] * w).round() as u8)
}

fn preview_pixels(view: &View, mask: &[bool]) -> Vec<u8> {
    let (w, h) = (view.width, view.height);
    let mut out = vec![0u8; 3 * w * h * 3];
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let row = v * 3 * w;
            let put = |out: &mut Vec<u8>, col: usize, c: [u8; 3]| {
                out[3 * (row + col)..3 * (row + col) + 3].copy_from_slice(&c);
            };
            put(&mut out, u, view.rgb[i]);
            if mask[i] {
                put(
                    &mut out,
                    w + u,
                    depth_colour(view.depth[i] / PREVIEW_MAX_DEPTH_M),
                );
            }
            let l = view.labels[i] as usize;
            if l < NUM_CLASSES {
                put(&mut out, 2 * w + u, CLASS_COLOURS[l]);
            }
        }
    }
    out
}

/// Size `[width, height]` of a PNG from its header, or an error naming the file.
pub fn png_size(path: &Path) -> Result<[usize; 2]> {
    let (w, h) = image::image_dimensions(path).map_err(|e| image_error(path, e))?;
    Ok([w as usize, h as usize])
}

fn image_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::Image {
            path: path.to_path_buf(),
            message: other.to_string(),
        },
    }
}

/// Decodes an image file (any format the `image` crate reads here: PNG).
pub fn decode(path: &Path) -> Result<DynamicImage> {
    image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?
        .decode()
        .map_err(|e| image_error(path, e))
}

fn check_size(path: &Path, img: &DynamicImage, size: [usize; 2]) -> Result<()> {
    let got = [img.width() as usize, img.height() as usize];
    if got != size {
        return Err(Error::data(
            path,
            format!(
                "image is {}x{} (WxH), expected {}x{}",
                got[0], got[1], size[0], size[1]
            ),
        ));
    }
    Ok(())
}

fn colour_error(path: &Path, img: &DynamicImage, expected: &str) -> Error {
    Error::data(
        path,
        format!("expected {expected}, found {:?}", img.color()),
    )
}

/// Reads an 8-bit RGB PNG of `size` `[width, height]` (row-major pixels).
pub fn read_rgb(path: &Path, size: [usize; 2]) -> Result<Vec<[u8; 3]>> {
    let img = decode(path)?;
    check_size(path, &img, size)?;
    match img {
        DynamicImage::ImageRgb8(b) => Ok(b.pixels().map(|p| p.0).collect()),
        other => Err(colour_error(path, &other, "8-bit RGB")),
    }
}

/// Reads a 16-bit depth PNG of `size` into metres (`value * scale`, 0 = missing).
pub fn read_depth(path: &Path, size: [usize; 2], scale: f64) -> Result<Vec<f32>> {
    let img = decode(path)?;
    check_size(path, &img, size)?;
    match img {
        DynamicImage::ImageLuma16(b) => Ok(b
            .as_raw()
            .iter()
            .map(|&v| (v as f64 * scale) as f32)
            .collect()),
        other => Err(colour_error(path, &other, "16-bit grey depth")),
    }
}

/// Reads a label PNG of `size`; every value must be a class id or [`UNKNOWN_PNG_LABEL`].
pub fn read_labels(path: &Path, size: [usize; 2]) -> Result<Vec<u8>> {
    let img = decode(path)?;
    check_size(path, &img, size)?;
    let DynamicImage::ImageLuma8(b) = img else {
        return Err(colour_error(path, &img, "8-bit grey labels"));
    };
    let raw = b.into_raw();
    if let Some(i) = raw
        .iter()
        .position(|&l| l as usize >= NUM_CLASSES && l != UNKNOWN_PNG_LABEL)
    {
        return Err(Error::data(
            path,
            format!(
                "unknown class index {} at pixel ({}, {}): expected 0..{} ({}) or {} (unknown)",
                raw[i],
                i % size[0],
                i / size[0],
                NUM_CLASSES - 1,
                CLASSES.join(", "),
                UNKNOWN_PNG_LABEL
            ),
        ));
    }
    Ok(raw)
}

/// Reads a mask PNG of `size`; values must be 0 or 255.
pub fn read_mask(path: &Path, size: [usize; 2]) -> Result<Vec<bool>> {
    let img = decode(path)?;
    check_size(path, &img, size)?;
    let DynamicImage::ImageLuma8(b) = img else {
        return Err(colour_error(path, &img, "8-bit grey mask"));
    };
    let raw = b.into_raw();
    if let Some(i) = raw.iter().position(|&m| m != 0 && m != 255) {
        return Err(Error::data(
            path,
            format!(
                "mask value {} at pixel ({}, {}): expected 0 or 255",
                raw[i],
                i % size[0],
                i / size[0]
            ),
        ));
    }
    Ok(raw.into_iter().map(|m| m == 255).collect())
}

/// Which split a sample belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Training samples.
    Train,
    /// Validation samples (model selection).
    Val,
    /// Held-out test samples (Stanford: area 5).
    Test,
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "train" => Ok(Split::Train),
            "val" => Ok(Split::Val),
            "test" => Ok(Split::Test),
            other => Err(format!(
                "unknown split `{other}` (expected train, val or test)"
            )),
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        })
    }
}

/// Sample ids per split.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Splits {
    /// Training ids.
    pub train: Vec<String>,
    /// Validation ids.
    pub val: Vec<String>,
    /// Test ids.
    pub test: Vec<String>,
}

impl Splits {
    /// The ids of one split.
    pub fn get(&self, split: Split) -> &[String] {
        match split {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// Every id, train then val then test.
    pub fn all(&self) -> impl Iterator<Item = &String> {
        self.train.iter().chain(&self.val).chain(&self.test)
    }
}

/// Counts recorded in the manifest.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Counts {
    /// Panoramas the views come from.
    pub panoramas: usize,
    /// Views rendered per panorama.
    pub views_per_panorama: usize,
    /// All samples (`panoramas x views_per_panorama`).
    pub samples: usize,
    /// Samples in the train split.
    pub train: usize,
    /// Samples in the val split.
    pub val: usize,
    /// Samples in the test split.
    pub test: usize,
}

/// `DATASET/manifest.json`. `config` is the generator's resolved settings for this data set
/// (what must match for `synth` to resume into the folder); readers need only the other fields.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Always [`crate::data::synth::GENERATOR`].
    pub generator: String,
    /// [`crate::data::synth::GENERATOR_VERSION`] of the build that wrote the set.
    pub generator_version: u32,
    /// False while `synth` is still writing (or was interrupted): readers refuse the set.
    pub complete: bool,
    /// Name of the set (e.g. `f195`).
    pub name: String,
    /// `pers`, `fisheye` or `rectified`.
    pub kind: String,
    /// The seed of scenes, orientations and splits.
    pub seed: u64,
    /// The camera file of the stored images, relative to the data set folder (`camera.toml`).
    pub camera: String,
    /// The camera file the set was made from, as given to `synth` (information only).
    pub camera_source: String,
    /// Where the panoramas came from (`procedural`, or the Stanford 2D-3D-S root), information.
    pub panorama_source: String,
    /// Stored image size, pixels.
    pub width: usize,
    /// Stored image height, pixels.
    pub height: usize,
    /// Metres per unit of the depth PNGs.
    pub depth_scale: f64,
    /// Class names in id order.
    pub classes: Vec<String>,
    /// Label PNG value of unknown pixels.
    pub unknown_label: u8,
    /// Sample counts.
    pub counts: Counts,
    /// Sample ids per split.
    pub splits: Splits,
    /// The generator's resolved settings.
    pub config: serde_json::Value,
}

/// Manifest file name inside a data set folder.
pub const MANIFEST: &str = "manifest.json";

impl Manifest {
    /// Serialises as pretty JSON with a trailing newline (stable key order: struct order).
    pub fn to_json(&self) -> String {
        let mut s = serde_json::to_string_pretty(self).expect("manifest serialises");
        s.push('\n');
        s
    }

    /// Reads `root/manifest.json` and checks that a build of this generator version wrote it.
    /// Does not check `complete` (see [`Manifest::check_complete`]).
    pub fn read(root: &Path) -> Result<Manifest> {
        let path = root.join(MANIFEST);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        Self::parse(&text, &path)
    }

    /// Parses manifest text; `path` names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Manifest> {
        use crate::data::synth::{GENERATOR, GENERATOR_VERSION};
        let value: serde_json::Value = serde_json::from_str(text)
            .map_err(|e| Error::data(path, format!("not valid JSON: {e}")))?;
        let generator = value.get("generator").and_then(|v| v.as_str());
        if generator != Some(GENERATOR) {
            return Err(Error::data(
                path,
                format!(
                    "field `generator`: expected \"{GENERATOR}\", found {}",
                    value
                        .get("generator")
                        .map_or("nothing".into(), |v| v.to_string())
                ),
            ));
        }
        let version = value.get("generator_version").and_then(|v| v.as_u64());
        if version != Some(GENERATOR_VERSION as u64) {
            return Err(Error::data(
                path,
                format!(
                    "field `generator_version`: the data set was made by generator version {}, \
                     this build reads version {GENERATOR_VERSION}; regenerate it with \
                     `calibconv synth --force`",
                    value
                        .get("generator_version")
                        .map_or("(missing)".into(), |v| v.to_string())
                ),
            ));
        }
        let m: Manifest = serde_json::from_value(value)
            .map_err(|e| Error::data(path, format!("malformed manifest: {e}")))?;
        if m.classes != CLASSES {
            return Err(Error::data(
                path,
                format!(
                    "field `classes`: expected {CLASSES:?}, found {:?}",
                    m.classes
                ),
            ));
        }
        if !(m.depth_scale.is_finite() && m.depth_scale > 0.0) {
            return Err(Error::data(
                path,
                format!("field `depth_scale`: must be > 0, found {}", m.depth_scale),
            ));
        }
        if m.unknown_label != UNKNOWN_PNG_LABEL {
            return Err(Error::data(
                path,
                format!(
                    "field `unknown_label`: expected {UNKNOWN_PNG_LABEL}, found {}",
                    m.unknown_label
                ),
            ));
        }
        Ok(m)
    }

    /// An error unless generation finished.
    pub fn check_complete(&self, root: &Path) -> Result<()> {
        if self.complete {
            Ok(())
        } else {
            Err(Error::data(
                root.join(MANIFEST),
                "field `complete` is false: generation was interrupted or is still running; \
                 run the same `calibconv synth` command again to finish it",
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_view() -> View {
        View {
            width: 3,
            height: 2,
            rgb: vec![
                [10, 20, 30],
                [0, 0, 0],
                [255, 1, 2],
                [4, 5, 6],
                [7, 8, 9],
                [1, 1, 1],
            ],
            depth: vec![1.2345, 0.0, 70.0, 2.0, 3.0, f32::NAN],
            labels: vec![0, 255, 12, 3, 4, 5],
            mask: vec![true, false, true, true, true, true],
        }
    }

    #[test]
    fn samples_round_trip_through_png() {
        let dir = tempfile::tempdir().unwrap();
        let enc = encode_sample(&tiny_view(), DEPTH_SCALE);
        assert_eq!(enc, encode_sample(&tiny_view(), DEPTH_SCALE));
        for (name, bytes) in SAMPLE_DIRS.iter().zip(enc.files()) {
            let p = sample_path(dir.path(), name, "a");
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, bytes).unwrap();
        }
        let p = |d: &str| sample_path(dir.path(), d, "a");
        assert_eq!(read_rgb(&p("rgb"), [3, 2]).unwrap(), tiny_view().rgb);
        let depth = read_depth(&p("depth"), [3, 2], DEPTH_SCALE).unwrap();
        // 1 mm quantisation; 70 m is beyond 65.535 m and NaN is missing: both stored as 0.
        assert!((depth[0] - 1.235).abs() < 1e-6, "{}", depth[0]);
        assert_eq!([depth[1], depth[2], depth[5]], [0.0; 3]);
        assert_eq!(
            read_labels(&p("labels"), [3, 2]).unwrap(),
            tiny_view().labels
        );
        let mask = read_mask(&p("mask"), [3, 2]).unwrap();
        assert_eq!(mask, vec![true, false, false, true, true, false]);
        assert_eq!(png_size(&p("previews")).unwrap(), [9, 2]);
    }

    #[test]
    fn bad_files_name_the_file_and_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let enc = encode_sample(&tiny_view(), DEPTH_SCALE);
        let p = dir.path().join("x.png");
        std::fs::write(&p, &enc.labels).unwrap();
        let e = read_labels(&p, [2, 3]).unwrap_err().to_string();
        assert!(
            e.contains("x.png") && e.contains("3x2") && e.contains("2x3"),
            "{e}"
        );
        let e = read_rgb(&p, [3, 2]).unwrap_err().to_string();
        assert!(e.contains("x.png") && e.contains("RGB"), "{e}");
        // A label 13 is not a class.
        let mut v = tiny_view();
        v.labels[4] = 13;
        std::fs::write(&p, encode_sample(&v, DEPTH_SCALE).labels).unwrap();
        let e = read_labels(&p, [3, 2]).unwrap_err().to_string();
        assert!(
            e.contains("x.png") && e.contains("class index 13") && e.contains("(1, 1)"),
            "{e}"
        );
        let e = read_rgb(&dir.path().join("missing.png"), [3, 2]).unwrap_err();
        assert!(matches!(e, Error::Io { .. }) && e.to_string().contains("missing.png"));
    }

    #[test]
    fn manifest_from_another_generator_version_is_refused() {
        let text = r#"{"generator": "calibconv synth", "generator_version": 0}"#;
        let e = Manifest::parse(text, Path::new("d/manifest.json"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("d/manifest.json") && e.contains("version 0"),
            "{e}"
        );
        let e = Manifest::parse(r#"{"generator": "other"}"#, Path::new("m.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("generator"), "{e}");
    }
}
