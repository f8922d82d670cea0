//! The panoramic part of Stanford 2D-3D-S (Armeni et al. 2017), decoded to the project's
//! 13 classes + unknown so that the same view synthesis runs on it.
//!
//! # Layout and encodings (as the dataset ships and public loaders read it)
//!
//! ```text
//! ROOT/assets/semantic_labels.json      JSON list of instance names, e.g. "chair_1_office_3_area_5"
//! ROOT/area_{1,2,3,4,5a,5b,6}/pano/rgb/camera_<uuid>_<room>_<i>_frame_equirectangular_domain_rgb.png
//! ROOT/area_*/pano/depth/..._domain_depth.png         16-bit, 1/512 m per unit, 65535 = missing
//! ROOT/area_*/pano/semantic/..._domain_semantic.png   RGB: index = R * 65536 + G * 256 + B
//! ```
//!
//! - The class of a semantic index is the part of its name before the first underscore;
//!   `<UNK>` (index 0) is unknown; the value `0x0D0D0D` (beyond the list) marks pixels without
//!   annotation and is unknown too. Any other index outside the list, or a name whose class is
//!   not one of the 13, is an error naming the file (it means a different or damaged release).
//! - Depth is the distance from the camera centre (as our panoramas), `value / 512` metres;
//!   `65535` and `0` are missing.
//! - Panoramas are 4096 x 2048 and equirectangular with the top row looking up, as
//!   [`crate::data::panorama`]; [`Stanford::load_scaled`] box-filters RGB down by an integer
//!   factor and takes depth and labels at each block's centre.
//! - Splits: the official fold 1 holds out area 5 (`area_5a`, `area_5b`) as **test**; `val` is
//!   a seeded fraction of the other areas' panoramas, the rest **train** (the paper trains and
//!   validates on areas 1, 2, 3, 4, 6 and evaluates on area 5).

use std::path::{Path, PathBuf};

use image::DynamicImage;

use crate::data::format::{decode, Split};
use crate::data::panorama::Panorama;
use crate::data::rng::tag;
use crate::data::source::{assign_splits, PanoramaSource};
use crate::data::{CLASSES, UNKNOWN_PNG_LABEL};
use crate::error::{Error, Result};

/// Depth PNG units per metre.
pub const DEPTH_UNITS_PER_M: f64 = 512.0;

/// Depth PNG value of missing pixels.
pub const DEPTH_MISSING: u16 = 65535;

/// Semantic PNG value of pixels without annotation.
pub const SEMANTIC_MISSING: u32 = 0x0D0D0D;

/// Areas held out for testing in the official fold 1.
pub const FOLD1_TEST_AREAS: [&str; 3] = ["area_5", "area_5a", "area_5b"];

/// `semantic_labels.json`: the class id (or unknown) of every semantic index.
#[derive(Clone, Debug, PartialEq)]
pub struct SemanticLabels {
    /// The file the list was read from.
    pub path: PathBuf,
    /// Per index: a class id in `CLASSES` order or [`UNKNOWN_PNG_LABEL`].
    pub classes: Vec<u8>,
}

impl SemanticLabels {
    /// Reads and decodes the label list.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path)
    }

    /// Decodes label-list text; `path` names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let names: Vec<String> = serde_json::from_str(text)
            .map_err(|e| Error::data(path, format!("expected a JSON list of names: {e}")))?;
        let classes = names
            .iter()
            .enumerate()
            .map(|(i, name)| {
                let class = name.split('_').next().unwrap_or("");
                if class == "<UNK>" {
                    return Ok(UNKNOWN_PNG_LABEL);
                }
                CLASSES
                    .iter()
                    .position(|&c| c == class)
                    .map(|c| c as u8)
                    .ok_or_else(|| {
                        Error::data(
                            path,
                            format!(
                                "entry {i} `{name}`: class `{class}` is not one of {} or <UNK>",
                                CLASSES.join(", ")
                            ),
                        )
                    })
            })
            .collect::<Result<Vec<u8>>>()?;
        Ok(SemanticLabels {
            path: path.to_path_buf(),
            classes,
        })
    }

    /// Class of a semantic pixel: `None` for an index outside the list that is not the
    /// missing value.
    pub fn class_of(&self, rgb: [u8; 3]) -> Option<u8> {
        let index = (rgb[0] as u32) << 16 | (rgb[1] as u32) << 8 | rgb[2] as u32;
        if index == SEMANTIC_MISSING {
            return Some(UNKNOWN_PNG_LABEL);
        }
        self.classes.get(index as usize).copied()
    }
}

/// The files of one panorama.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StanfordPano {
    /// `area_1`, ..., `area_5a`, ...
    pub area: String,
    /// The file name without `_rgb.png` (and `_frame_equirectangular_domain`).
    pub stem: String,
    /// `pano/rgb/..._rgb.png`.
    pub rgb: PathBuf,
    /// `pano/depth/..._depth.png`.
    pub depth: PathBuf,
    /// `pano/semantic/..._semantic.png`.
    pub semantic: PathBuf,
}

impl StanfordPano {
    /// `AREA_STEM`, used as the prefix of sample ids.
    pub fn name(&self) -> String {
        format!("{}_{}", self.area, self.stem)
    }

    /// Whether the panorama is in the test split of fold 1.
    pub fn is_fold1_test(&self) -> bool {
        FOLD1_TEST_AREAS.contains(&self.area.as_str())
    }
}

/// A Stanford 2D-3D-S tree: the label list and every panorama, sorted by area then file name.
#[derive(Clone, Debug)]
pub struct Stanford {
    /// The dataset root.
    pub root: PathBuf,
    /// The decoded label list.
    pub labels: SemanticLabels,
    /// Every panorama, sorted.
    pub panoramas: Vec<StanfordPano>,
}

fn sorted_entries(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        out.push(e.map_err(|e| Error::io(dir, e))?.path());
    }
    out.sort();
    Ok(out)
}

impl Stanford {
    /// Scans `root/area_*/pano/rgb/*_rgb.png` and checks that every panorama has its depth and
    /// semantic files; reads the label list at `labels`.
    pub fn open(root: &Path, labels: &Path) -> Result<Self> {
        let labels = SemanticLabels::load(labels)?;
        let mut panoramas = Vec::new();
        for area_dir in sorted_entries(root)? {
            let area = area_dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if !area.starts_with("area_") || !area_dir.is_dir() {
                continue;
            }
            let rgb_dir = area_dir.join("pano/rgb");
            if !rgb_dir.is_dir() {
                continue;
            }
            for rgb in sorted_entries(&rgb_dir)? {
                let file = rgb
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                let Some(base) = file.strip_suffix("_rgb.png") else {
                    continue;
                };
                let depth = area_dir.join(format!("pano/depth/{base}_depth.png"));
                let semantic = area_dir.join(format!("pano/semantic/{base}_semantic.png"));
                for p in [&depth, &semantic] {
                    if !p.is_file() {
                        return Err(Error::data(
                            p,
                            format!("missing: the companion of {}", rgb.display()),
                        ));
                    }
                }
                let stem = base
                    .strip_suffix("_frame_equirectangular_domain")
                    .unwrap_or(base)
                    .to_string();
                panoramas.push(StanfordPano {
                    area: area.clone(),
                    stem,
                    rgb,
                    depth,
                    semantic,
                });
            }
        }
        if panoramas.is_empty() {
            return Err(Error::data(
                root,
                "no panoramas found: expected area_*/pano/rgb/*_rgb.png below this folder",
            ));
        }
        Ok(Stanford {
            root: root.to_path_buf(),
            labels,
            panoramas,
        })
    }

    /// Decodes panorama `i` at full resolution.
    pub fn load(&self, i: usize) -> Result<Panorama> {
        let p = &self.panoramas[i];
        let rgb_img = decode(&p.rgb)?;
        let (w, h) = (rgb_img.width() as usize, rgb_img.height() as usize);
        if w != 2 * h || h == 0 {
            return Err(Error::data(
                &p.rgb,
                format!("panorama is {w}x{h} (WxH), expected width = 2 height"),
            ));
        }
        let rgb = rgb8_pixels(rgb_img, &p.rgb, "8-bit RGB(A)")?;
        let same_size = |path: &Path, img: &DynamicImage| {
            if (img.width() as usize, img.height() as usize) == (w, h) {
                Ok(())
            } else {
                Err(Error::data(
                    path,
                    format!(
                        "image is {}x{}, its RGB panorama {} is {w}x{h}",
                        img.width(),
                        img.height(),
                        p.rgb.display()
                    ),
                ))
            }
        };
        let depth_img = decode(&p.depth)?;
        same_size(&p.depth, &depth_img)?;
        let depth: Vec<f32> = match depth_img {
            DynamicImage::ImageLuma16(b) => b
                .as_raw()
                .iter()
                .map(|&v| {
                    if v == DEPTH_MISSING || v == 0 {
                        0.0
                    } else {
                        (v as f64 / DEPTH_UNITS_PER_M) as f32
                    }
                })
                .collect(),
            other => {
                return Err(Error::data(
                    &p.depth,
                    format!("expected 16-bit grey depth, found {:?}", other.color()),
                ))
            }
        };
        let sem_img = decode(&p.semantic)?;
        same_size(&p.semantic, &sem_img)?;
        let sem = rgb8_pixels(sem_img, &p.semantic, "8-bit RGB semantic indices")?;
        let mut labels = Vec::with_capacity(w * h);
        for (k, px) in sem.iter().enumerate() {
            match self.labels.class_of(*px) {
                Some(c) => labels.push(c),
                None => {
                    let index = (px[0] as u32) << 16 | (px[1] as u32) << 8 | px[2] as u32;
                    return Err(Error::data(
                        &p.semantic,
                        format!(
                            "unknown class index {index} (0x{index:06X}) at pixel ({}, {}): {} \
                             lists {} names and 0x{SEMANTIC_MISSING:06X} marks missing labels",
                            k % w,
                            k / w,
                            self.labels.path.display(),
                            self.labels.classes.len()
                        ),
                    ));
                }
            }
        }
        let pano = Panorama {
            width: w,
            height: h,
            rgb,
            depth,
            labels,
        };
        pano.check()?;
        Ok(pano)
    }

    /// Panorama `i` scaled to `height` rows (an integer divisor of its height); see
    /// [`Panorama::downsample`].
    pub fn load_scaled(&self, i: usize, height: usize) -> Result<Panorama> {
        let full = self.load(i)?;
        if height == 0 || full.height % height != 0 {
            return Err(Error::data(
                &self.panoramas[i].rgb,
                format!(
                    "panorama height {} is not a multiple of the requested height {height} \
                     (panoramas.height / --pano-height)",
                    full.height
                ),
            ));
        }
        full.downsample(full.height / height)
    }
}

/// The pixels of an 8-bit RGB or RGBA image read from `path` (alpha dropped), or an error
/// saying it is not `expected`.
fn rgb8_pixels(img: DynamicImage, path: &Path, expected: &str) -> Result<Vec<[u8; 3]>> {
    match img {
        DynamicImage::ImageRgb8(b) => Ok(b.pixels().map(|px| px.0).collect()),
        DynamicImage::ImageRgba8(b) => Ok(b.pixels().map(|px| [px[0], px[1], px[2]]).collect()),
        other => Err(Error::data(
            path,
            format!("expected {expected}, found {:?}", other.color()),
        )),
    }
}

/// Stanford panoramas as a [`PanoramaSource`] for `synth`: a subset, fold-1 splits, a height.
pub struct StanfordSource {
    data: Stanford,
    selected: Vec<usize>,
    splits: Vec<Split>,
    height: usize,
}

impl StanfordSource {
    /// Opens the tree; `count` = 0 takes every panorama, otherwise `count` evenly spaced ones
    /// (over the sorted list, so every area is represented); `val` is the fraction of the
    /// non-test panoramas used for validation (chosen by `seed`).
    pub fn open(
        root: &Path,
        labels: &Path,
        count: usize,
        height: usize,
        val: f64,
        seed: u64,
    ) -> Result<Self> {
        let data = Stanford::open(root, labels)?;
        let n = data.panoramas.len();
        // Splits over the whole list, so a subset agrees with the full set.
        let non_test: Vec<usize> = (0..n)
            .filter(|&i| !data.panoramas[i].is_fold1_test())
            .collect();
        let val_of = assign_splits(non_test.len(), val, 0.0, seed);
        let mut all = vec![Split::Test; n];
        for (k, &i) in non_test.iter().enumerate() {
            all[i] = val_of[k];
        }
        let selected: Vec<usize> = if count == 0 || count >= n {
            (0..n).collect()
        } else {
            (0..count).map(|k| k * n / count).collect()
        };
        let splits = selected.iter().map(|&i| all[i]).collect();
        Ok(StanfordSource {
            data,
            selected,
            splits,
            height,
        })
    }
}

impl PanoramaSource for StanfordSource {
    fn len(&self) -> usize {
        self.selected.len()
    }
    fn name(&self, i: usize) -> String {
        self.data.panoramas[self.selected[i]].name()
    }
    fn key(&self, i: usize) -> u64 {
        tag(&self.name(i))
    }
    fn split(&self, i: usize) -> Split {
        self.splits[i]
    }
    fn load(&self, i: usize) -> Result<Panorama> {
        self.data.load_scaled(self.selected[i], self.height)
    }
    fn describe(&self) -> String {
        format!("stanford 2D-3D-S at {}", self.data.root.display())
    }
}

/// Writes a tiny fake Stanford 2D-3D-S tree in the real layout and encodings (for tests and
/// demos without the licensed data): `areas` each get `per_area` panoramas of `2 h x h`
/// pixels whose semantic image uses every class, `<UNK>` and the missing value, and whose
/// depth holds a missing pixel.
pub fn write_fake_tree(root: &Path, areas: &[&str], per_area: usize, h: usize) -> Result<()> {
    use crate::io::write_bytes_atomic;
    use image::codecs::png::PngEncoder;
    use image::{ExtendedColorType, ImageEncoder};

    let mut names = vec!["<UNK>".to_string()];
    for (k, c) in CLASSES.iter().enumerate() {
        names.push(format!("{c}_{}_office_1_area_1", k + 1));
    }
    let labels = serde_json::to_string(&names).expect("names serialise");
    write_bytes_atomic(&root.join("assets/semantic_labels.json"), labels.as_bytes())?;
    let w = 2 * h;
    let png = |bytes: &[u8], colour: ExtendedColorType| {
        let mut out = Vec::new();
        PngEncoder::new(&mut out)
            .write_image(bytes, w as u32, h as u32, colour)
            .expect("in-memory PNG");
        out
    };
    for (a, area) in areas.iter().enumerate() {
        for n in 0..per_area {
            let base = format!("camera_{a:02x}{n:030x}_office_{n}_frame_equirectangular_domain");
            let dir = root.join(area).join("pano");
            let mut rgb = Vec::new();
            let mut depth = Vec::new();
            let mut sem = Vec::new();
            for v in 0..h {
                for u in 0..w {
                    // Label bands by column: index 1..=13 (the classes), 0 (<UNK>), missing.
                    let band = (u * 15 / w + n) % 15;
                    let index: u32 = match band {
                        13 => 0,
                        14 => SEMANTIC_MISSING,
                        b => b as u32 + 1,
                    };
                    sem.extend([(index >> 16) as u8, (index >> 8) as u8, index as u8]);
                    rgb.extend([(u * 255 / w) as u8, (v * 255 / h) as u8, (a * 40 + n) as u8]);
                    // 1 m + 1 cm per row, in 1/512 m units; one missing pixel per panorama.
                    let d: u16 = if (u, v) == (1, 1) {
                        DEPTH_MISSING
                    } else {
                        ((1.0 + 0.01 * v as f64) * DEPTH_UNITS_PER_M).round() as u16
                    };
                    depth.extend(d.to_ne_bytes());
                }
            }
            write_bytes_atomic(
                &dir.join(format!("rgb/{base}_rgb.png")),
                &png(&rgb, ExtendedColorType::Rgb8),
            )?;
            write_bytes_atomic(
                &dir.join(format!("depth/{base}_depth.png")),
                &png(&depth, ExtendedColorType::L16),
            )?;
            write_bytes_atomic(
                &dir.join(format!("semantic/{base}_semantic.png")),
                &png(&sem, ExtendedColorType::Rgb8),
            )?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fake(areas: &[&str]) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        write_fake_tree(dir.path(), areas, 2, 8).unwrap();
        dir
    }

    fn open(dir: &Path) -> Result<Stanford> {
        Stanford::open(dir, &dir.join("assets/semantic_labels.json"))
    }

    #[test]
    fn decodes_labels_depth_and_rgb_of_the_real_encodings() {
        let dir = fake(&["area_1", "area_5a"]);
        let s = open(dir.path()).unwrap();
        assert_eq!(s.panoramas.len(), 4);
        assert_eq!(s.panoramas[0].area, "area_1");
        assert!(
            s.panoramas[0].stem.ends_with("_office_0"),
            "{}",
            s.panoramas[0].stem
        );
        let p = s.load(0).unwrap();
        assert_eq!((p.width, p.height), (16, 8));
        // Column bands: u * 15 / 16 -> band; band b < 13 is class b, 13 <UNK>, 14 missing.
        for u in 0..16 {
            let band = u * 15 / 16;
            let expect = if band < 13 {
                band as u8
            } else {
                UNKNOWN_PNG_LABEL
            };
            assert_eq!(p.labels[3 * 16 + u], expect, "column {u}");
        }
        assert_eq!(p.depth[16 + 1], 0.0); // 65535 = missing
        assert!((p.depth[2 * 16 + 5] - 1.02).abs() < 1e-3); // 522 / 512 m
        assert_eq!(p.rgb[16 + 8], [127, 31, 0]);
        // Fold 1: area 5a is the test split.
        assert!(s.panoramas[2].is_fold1_test() && !s.panoramas[0].is_fold1_test());
        let src = StanfordSource::open(
            dir.path(),
            &dir.path().join("assets/semantic_labels.json"),
            0,
            4,
            0.5,
            1,
        )
        .unwrap();
        assert_eq!(src.split(2), Split::Test);
        assert_eq!(src.split(3), Split::Test);
        assert_ne!(src.split(0), Split::Test);
        assert_eq!(src.load(1).unwrap().height, 4);
        assert!(src.name(0).starts_with("area_1_camera_"));
    }

    #[test]
    fn unknown_class_index_and_bad_files_are_errors_naming_the_file() {
        let dir = fake(&["area_1"]);
        let s = open(dir.path()).unwrap();
        // Rewrite a semantic image with index 500 (beyond the 14 names).
        let p = &s.panoramas[0];
        let mut img = image::open(&p.semantic).unwrap().to_rgb8();
        img.put_pixel(3, 2, image::Rgb([0, 1, 244]));
        img.save(&p.semantic).unwrap();
        let e = s.load(0).unwrap_err().to_string();
        assert!(
            e.contains("_semantic.png") && e.contains("index 500") && e.contains("(3, 2)"),
            "{e}"
        );
        // A depth image of the wrong size.
        let q = &s.panoramas[1];
        image::GrayImage::new(4, 2).save(&q.depth).unwrap();
        let e = s.load(1).unwrap_err().to_string();
        assert!(e.contains("_depth.png") && e.contains("4x2"), "{e}");
        // A missing companion file.
        std::fs::remove_file(&q.semantic).unwrap();
        let e = open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("_semantic.png") && e.contains("missing"), "{e}");
        // A label list naming a class that is not one of the 13.
        let e = SemanticLabels::parse(r#"["<UNK>", "sink_1_x"]"#, Path::new("l.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("l.json") && e.contains("sink"), "{e}");
        // No panoramas at all.
        let empty = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(empty.path().join("assets")).unwrap();
        std::fs::write(empty.path().join("assets/semantic_labels.json"), "[]").unwrap();
        let e = open(empty.path()).unwrap_err().to_string();
        assert!(e.contains("no panoramas"), "{e}");
    }
}
