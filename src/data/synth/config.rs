//! The configuration of `synth` (see the [module docs](super) for the file): the `Raw*` types
//! as written, [`RawSynthConfig::resolve`] checking them into a [`SynthPlan`].

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::{self, Camera, CameraModel, PixelConvention};
use crate::data::format::DEPTH_SCALE;
use crate::data::source::{PanoramaSource, ProceduralSource};
use crate::data::views::{max_ray_angle, rectified_camera, ViewSampling};
use crate::error::{Error, Result};

/// `data/synth.toml`, the embedded default configuration.
pub const DEFAULT_CONFIG: &str = include_str!("../../../data/synth.toml");

/// The camera files [`DEFAULT_CONFIG`] names, embedded in the binary as well, so that the
/// embedded default works from any directory: `(path as written in the configuration, text)`.
/// A set of [`RawSynthConfig::default_config`] whose camera is one of these paths reads this
/// text instead of the file on disk (the same bytes, compiled from this repository).
pub const DEFAULT_CAMERAS: &[(&str, &str)] = &[
    (
        "data/cameras/f195.toml",
        include_str!("../../../data/cameras/f195.toml"),
    ),
    (
        "data/cameras/f165.toml",
        include_str!("../../../data/cameras/f165.toml"),
    ),
    (
        "data/cameras/pers.toml",
        include_str!("../../../data/cameras/pers.toml"),
    ),
];

/// Where panoramas come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceKind {
    /// Rendered by [`crate::data::panorama`].
    #[default]
    Procedural,
    /// Read from a Stanford 2D-3D-S copy.
    Stanford,
}

/// What a set's images are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ViewKind {
    /// A pinhole camera.
    Pers,
    /// A fisheye (Kannala-Brandt) camera.
    Fisheye,
    /// A fisheye image re-projected to a pinhole camera (FOV < 180 deg).
    Rectified,
}

impl ViewKind {
    /// The name used in files: `pers`, `fisheye`, `rectified`.
    pub fn as_str(&self) -> &'static str {
        let (name, _) = (Self::NAMES.iter())
            .find(|(_, kind)| kind == self)
            .expect("every kind has a name");
        name
    }
}

calibconv_geometry::from_str_by_name!(ViewKind, "kind", {
    "pers" => Pers,
    "fisheye" => Fisheye,
    "rectified" => Rectified,
});

/// Split fractions of the panoramas.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSplit {
    /// Fraction of panoramas for training.
    pub train: f64,
    /// Fraction for validation.
    pub val: f64,
    /// Fraction for testing (procedural only).
    pub test: f64,
}

impl Default for RawSplit {
    fn default() -> Self {
        RawSplit {
            train: 0.8,
            val: 0.1,
            test: 0.1,
        }
    }
}

/// `[panoramas]` as written.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawPanoramas {
    /// Where panoramas come from.
    #[serde(default)]
    pub source: SourceKind,
    /// Procedural: how many; Stanford: 0 = all, N = an evenly spaced subset.
    pub count: usize,
    /// Panorama height in pixels (width = 2 height).
    pub height: usize,
    /// Split fractions.
    #[serde(default)]
    pub split: RawSplit,
    /// Stanford 2D-3D-S root (source = "stanford").
    pub stanford_root: Option<PathBuf>,
    /// Its label list (default: ROOT/assets/semantic_labels.json).
    pub stanford_labels: Option<PathBuf>,
}

/// `[views]` as written.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawViews {
    /// Views per panorama and set.
    pub per_panorama: usize,
    /// Pitch is uniform in `[-max, max]`, degrees.
    pub pitch_max_deg: f64,
    /// Roll is uniform in `[-max, max]`, degrees.
    pub roll_max_deg: f64,
    /// `k x k` RGB rays per pixel.
    pub supersample: usize,
}

impl Default for RawViews {
    fn default() -> Self {
        let s = ViewSampling::default();
        RawViews {
            per_panorama: 4,
            pitch_max_deg: s.pitch_max_deg,
            roll_max_deg: s.roll_max_deg,
            supersample: 2,
        }
    }
}

/// One `[[set]]` as written.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSet {
    /// Folder name.
    pub name: String,
    /// What the images are.
    pub kind: ViewKind,
    /// Camera file (the fisheye for `rectified`).
    pub camera: PathBuf,
    /// Stored image width, pixels.
    pub width: usize,
    /// Rectified only: the pinhole's horizontal field of view, degrees.
    pub rectify_hfov_deg: Option<f64>,
}

/// A synthesis configuration file as written (the CLI edits its public fields for flags, then
/// calls [`RawSynthConfig::resolve`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSynthConfig {
    /// Seed of scenes, orientations and splits.
    pub seed: u64,
    /// Output root: each set goes to `out/name`.
    pub out: PathBuf,
    /// `[panoramas]`.
    pub panoramas: RawPanoramas,
    /// `[views]`.
    #[serde(default)]
    pub views: RawViews,
    /// The `[[set]]`s.
    #[serde(rename = "set")]
    pub sets: Vec<RawSet>,
    /// Camera files read from the binary instead of the disk, `(path, text)`: a set whose
    /// `camera` is one of these paths (compared as written) uses the text. [`DEFAULT_CAMERAS`]
    /// for [`RawSynthConfig::default_config`], empty for configurations read from files; clear
    /// it to read every camera from disk.
    #[serde(skip)]
    pub embedded_cameras: &'static [(&'static str, &'static str)],
}

/// Smallest panorama height accepted.
const MIN_PANO_HEIGHT: usize = 8;
/// Smallest stored image width accepted.
const MIN_WIDTH: usize = 8;

impl RawSynthConfig {
    /// Parses configuration text; `path` names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        toml::from_str(text).map_err(|e| Error::Toml {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })
    }

    /// Reads a configuration file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path)
    }

    /// The embedded default (`data/synth.toml`), with its cameras embedded too
    /// ([`DEFAULT_CAMERAS`]): it resolves in any working directory.
    pub fn default_config() -> Self {
        let mut raw = Self::parse(DEFAULT_CONFIG, Path::new("<embedded data/synth.toml>"))
            .expect("the embedded default configuration parses");
        raw.embedded_cameras = DEFAULT_CAMERAS;
        raw
    }

    /// A set's camera: the embedded text if `path` is one of [`Self::embedded_cameras`], else
    /// the file.
    fn load_camera(&self, path: &Path) -> Result<Camera> {
        match self
            .embedded_cameras
            .iter()
            .find(|(name, _)| Path::new(name) == path)
        {
            Some((name, text)) => camera::parse(text, Path::new(name)),
            None => camera::load(path),
        }
    }

    /// Checks every field and loads the cameras; `path` names the configuration in errors.
    pub fn resolve(&self, path: &Path) -> Result<SynthPlan> {
        let source = self.panoramas.resolve(path)?;
        let v = &self.views;
        v.check(path)?;
        if self.sets.is_empty() {
            return Err(field_error(path, "set", "no [[set]] to generate".into()));
        }
        let mut names = HashSet::new();
        let sets = (self.sets.iter().enumerate())
            .map(|(i, raw)| self.resolve_set(path, i, raw, &mut names))
            .collect::<Result<Vec<_>>>()?;
        Ok(SynthPlan {
            seed: self.seed,
            out: self.out.clone(),
            source,
            per_panorama: v.per_panorama,
            sampling: ViewSampling {
                pitch_max_deg: v.pitch_max_deg,
                roll_max_deg: v.roll_max_deg,
            },
            supersample: v.supersample,
            sets,
        })
    }

    /// `set[i]` checked (a folder name not in `names` yet, which it joins; a width; a camera of
    /// the kind) with its camera loaded and scaled to the stored width.
    fn resolve_set(
        &self,
        path: &Path,
        i: usize,
        raw: &RawSet,
        names: &mut HashSet<String>,
    ) -> Result<SetPlan> {
        let bad = |field: &str, msg: String| field_error(path, field, msg);
        let field = |f: &str| format!("set[{i}].{f}");
        let ok_name = !raw.name.is_empty()
            && raw
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            && !raw.name.starts_with('.');
        if !ok_name {
            return Err(bad(
                &field("name"),
                format!(
                    "`{}` is not a folder name (letters, digits, - _ . only)",
                    raw.name
                ),
            ));
        }
        if !names.insert(raw.name.clone()) {
            return Err(bad(&field("name"), format!("`{}` appears twice", raw.name)));
        }
        if raw.width < MIN_WIDTH {
            return Err(bad(
                &field("width"),
                format!("must be >= {MIN_WIDTH}, found {}", raw.width),
            ));
        }
        let cam = self.load_camera(&raw.camera).map_err(|e| {
            Error::data(
                path,
                format!("field `{}`: cannot use camera file: {e}", field("camera")),
            )
        })?;
        let scale = raw.width as f64 / cam.size()[0] as f64;
        let scaled = cam.rescaled([scale, scale], PixelConvention::HalfPixel);
        let model_error = |want: &str| {
            bad(
                &field("camera"),
                format!(
                    "kind `{}` needs a {want} camera, {} is not one",
                    raw.kind.as_str(),
                    raw.camera.display()
                ),
            )
        };
        if raw.rectify_hfov_deg.is_some() && raw.kind != ViewKind::Rectified {
            return Err(bad(
                &field("rectify_hfov_deg"),
                "only for kind = \"rectified\"".into(),
            ));
        }
        let (camera, fisheye) = match raw.kind {
            ViewKind::Pers => {
                if !matches!(cam, Camera::Pinhole(_) | Camera::PinholeRadTan(_)) {
                    return Err(model_error("perspective (pinhole, pinhole-radtan)"));
                }
                (scaled, None)
            }
            ViewKind::Fisheye => {
                if max_ray_angle(&cam).is_none() {
                    return Err(model_error(
                        "fisheye (kannala-brandt, double-sphere, unified, extended-unified, \
                         scaramuzza)",
                    ));
                }
                (scaled, None)
            }
            ViewKind::Rectified => {
                let pin = rectified_camera(&scaled, raw.rectify_hfov_deg)
                    .map_err(|e| bad(&field("camera"), e.to_string()))?;
                (pin, Some(scaled))
            }
        };
        Ok(SetPlan {
            name: raw.name.clone(),
            kind: raw.kind,
            camera_path: raw.camera.clone(),
            camera,
            fisheye,
            rectify_hfov_deg: raw.rectify_hfov_deg,
        })
    }
}

/// The error of a configuration `path` whose `field` is invalid.
fn field_error(path: &Path, field: &str, msg: String) -> Error {
    Error::data(path, format!("field `{field}`: {msg}"))
}

impl RawPanoramas {
    /// The checked source: a height, split fractions in `[0, 1]` summing to 1, a count for
    /// procedural panoramas, a root for Stanford's.
    fn resolve(&self, path: &Path) -> Result<SourceSpec> {
        let bad = |field: &str, msg: String| field_error(path, field, msg);
        let p = self;
        if p.height < MIN_PANO_HEIGHT {
            return Err(bad(
                "panoramas.height",
                format!("must be >= {MIN_PANO_HEIGHT}, found {}", p.height),
            ));
        }
        let s = p.split;
        for (f, v) in [("train", s.train), ("val", s.val), ("test", s.test)] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(bad(
                    &format!("panoramas.split.{f}"),
                    format!("must be in [0, 1], found {v}"),
                ));
            }
        }
        if (s.train + s.val + s.test - 1.0).abs() > 1e-9 {
            return Err(bad(
                "panoramas.split",
                format!(
                    "train + val + test must be 1, found {}",
                    s.train + s.val + s.test
                ),
            ));
        }
        Ok(match p.source {
            SourceKind::Procedural => {
                if p.count == 0 {
                    return Err(bad("panoramas.count", "must be > 0".into()));
                }
                SourceSpec::Procedural {
                    count: p.count,
                    height: p.height,
                    split: s,
                }
            }
            SourceKind::Stanford => {
                let root = p.stanford_root.clone().ok_or_else(|| {
                    bad(
                        "panoramas.stanford_root",
                        "required when source = \"stanford\"".into(),
                    )
                })?;
                SourceSpec::Stanford {
                    labels: p
                        .stanford_labels
                        .clone()
                        .unwrap_or_else(|| root.join("assets/semantic_labels.json")),
                    root,
                    count: p.count,
                    height: p.height,
                    val: s.val,
                }
            }
        })
    }
}

impl RawViews {
    /// Views per panorama > 0, supersampling in `1..=8`, pitch in `[0, 90)`, roll in `[0, 180]`.
    fn check(&self, path: &Path) -> Result<()> {
        let bad = |field: &str, msg: String| field_error(path, field, msg);
        let v = self;
        if v.per_panorama == 0 {
            return Err(bad("views.per_panorama", "must be > 0".into()));
        }
        if !(1..=8).contains(&v.supersample) {
            return Err(bad(
                "views.supersample",
                format!("must be in 1..=8, found {}", v.supersample),
            ));
        }
        if !(v.pitch_max_deg.is_finite() && (0.0..90.0).contains(&v.pitch_max_deg)) {
            return Err(bad(
                "views.pitch_max_deg",
                format!("must be in [0, 90), found {}", v.pitch_max_deg),
            ));
        }
        if !(v.roll_max_deg.is_finite() && (0.0..=180.0).contains(&v.roll_max_deg)) {
            return Err(bad(
                "views.roll_max_deg",
                format!("must be in [0, 180], found {}", v.roll_max_deg),
            ));
        }
        Ok(())
    }
}

/// Where the panoramas of a plan come from, resolved.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceSpec {
    /// Procedural panoramas.
    Procedural {
        /// How many.
        count: usize,
        /// Height in pixels.
        height: usize,
        /// Split fractions.
        split: RawSplit,
    },
    /// Stanford 2D-3D-S panoramas.
    Stanford {
        /// Dataset root.
        root: PathBuf,
        /// Label list.
        labels: PathBuf,
        /// 0 = all.
        count: usize,
        /// Height in pixels.
        height: usize,
        /// Validation fraction of the non-test areas.
        val: f64,
    },
}

/// One data set to write, resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct SetPlan {
    /// Folder name.
    pub name: String,
    /// What the images are.
    pub kind: ViewKind,
    /// The camera file as given.
    pub camera_path: PathBuf,
    /// The camera of the stored images (scaled to the stored width; the pinhole for rectified).
    pub camera: Camera,
    /// Rectified sets: the fisheye rendered first, at the stored width.
    pub fisheye: Option<Camera>,
    /// Rectified only: the pinhole's horizontal FOV, if chosen.
    pub rectify_hfov_deg: Option<f64>,
}

/// A resolved configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthPlan {
    /// Seed of scenes, orientations and splits.
    pub seed: u64,
    /// Output root.
    pub out: PathBuf,
    /// Where panoramas come from.
    pub source: SourceSpec,
    /// Views per panorama and set.
    pub per_panorama: usize,
    /// How orientations are drawn.
    pub sampling: ViewSampling,
    /// `k x k` RGB rays per pixel.
    pub supersample: usize,
    /// The sets to write.
    pub sets: Vec<SetPlan>,
}

impl SynthPlan {
    /// The panorama source of the plan (scans the Stanford tree when there is one).
    pub fn open_source(&self) -> Result<Box<dyn PanoramaSource>> {
        match &self.source {
            SourceSpec::Procedural {
                count,
                height,
                split,
            } => Ok(Box::new(ProceduralSource::new(
                self.seed, *count, *height, split.val, split.test,
            ))),
            SourceSpec::Stanford {
                root,
                labels,
                count,
                height,
                val,
            } => Ok(Box::new(crate::data::stanford::StanfordSource::open(
                root, labels, *count, *height, *val, self.seed,
            )?)),
        }
    }

    /// The folder of a set: `out/name`.
    pub fn set_dir(&self, set: &SetPlan) -> PathBuf {
        self.out.join(&set.name)
    }

    /// The settings recorded as the manifest's `config` (compared on resume).
    pub(crate) fn manifest_config(&self, set: &SetPlan) -> serde_json::Value {
        let source = match &self.source {
            SourceSpec::Procedural {
                count,
                height,
                split,
            } => serde_json::json!({
                "procedural": {"count": count, "height": height, "split": split}
            }),
            // The root path is not compared (a moved copy is the same data); the panorama
            // list is, through the manifest's splits.
            SourceSpec::Stanford {
                count, height, val, ..
            } => serde_json::json!({
                "stanford": {"count": count, "height": height, "val": val}
            }),
        };
        let canonical = serde_json::json!({
            "kind": set.kind.as_str(),
            "camera": camera::to_toml(&set.camera, &[], None, None),
            "fisheye": set.fisheye.as_ref().map(|c| camera::to_toml(c, &[], None, None)),
            "rectify_hfov_deg": set.rectify_hfov_deg,
            "source": source,
            "views": {
                "per_panorama": self.per_panorama,
                "pitch_max_deg": self.sampling.pitch_max_deg,
                "roll_max_deg": self.sampling.roll_max_deg,
                "supersample": self.supersample,
            },
            "depth_scale": DEPTH_SCALE,
        });
        // Through text and back, so it compares equal to what a reader parses from the file.
        serde_json::from_str(&canonical.to_string()).expect("JSON round trip")
    }
}

/// The default configuration's sets, small: `count` panoramas `height` high, `per_panorama`
/// views of each set, `width` px wide, no supersampling, cameras read from this repository;
/// written to `out`.
#[cfg(test)]
pub(crate) fn tiny_config(
    out: &Path,
    [count, height, per_panorama, width]: [usize; 4],
) -> RawSynthConfig {
    let mut raw = RawSynthConfig::default_config();
    raw.out = out.to_path_buf();
    raw.panoramas.count = count;
    raw.panoramas.height = height;
    raw.views.per_panorama = per_panorama;
    raw.views.supersample = 1;
    for s in raw.sets.iter_mut() {
        s.camera = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(&s.camera);
        s.width = width;
    }
    raw
}

/// A plan of the default configuration's four sets, tiny (3 panoramas 16 high, 2 views, 16 px
/// wide), cameras read from this repository; written to `out`.
#[cfg(test)]
pub(crate) fn tiny_plan(out: &Path) -> SynthPlan {
    let raw = tiny_config(out, [3, 16, 2, 16]);
    raw.resolve(Path::new("test.toml")).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_config_resolves_to_the_four_paper_sets() {
        let plan = tiny_plan(Path::new("/tmp/unused"));
        let kinds: Vec<_> = plan
            .sets
            .iter()
            .map(|s| (s.name.as_str(), s.kind))
            .collect();
        assert_eq!(
            kinds,
            [
                ("f195", ViewKind::Fisheye),
                ("f165", ViewKind::Fisheye),
                ("pers", ViewKind::Pers),
                ("rect-f165", ViewKind::Rectified)
            ]
        );
        // 1080x960 scaled to 16 wide: 16 x round(14.22) = 14.
        assert_eq!(plan.sets[0].camera.size(), [16, 14]);
        assert!(matches!(plan.sets[3].camera, Camera::Pinhole(_)));
    }

    #[test]
    fn the_default_configs_cameras_are_embedded_and_equal_the_shipped_files() {
        let raw = RawSynthConfig::default_config();
        for set in &raw.sets {
            assert!(
                DEFAULT_CAMERAS
                    .iter()
                    .any(|(name, _)| Path::new(name) == set.camera),
                "{} is not embedded",
                set.camera.display()
            );
        }
        for (name, text) in DEFAULT_CAMERAS {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(name);
            assert_eq!(*text, std::fs::read_to_string(&path).unwrap(), "{name}");
        }
        // A configuration read from a file reads its cameras from disk.
        let from_file = RawSynthConfig::parse(DEFAULT_CONFIG, Path::new("c.toml")).unwrap();
        assert!(from_file.embedded_cameras.is_empty());
    }

    #[test]
    fn bad_configs_name_the_field() {
        let dir = env!("CARGO_MANIFEST_DIR");
        let mut raw = RawSynthConfig::default_config();
        raw.sets[0].camera = PathBuf::from(dir).join("data/cameras/f195.toml");
        raw.sets.truncate(1);
        let check = |raw: &RawSynthConfig, field: &str| {
            let e = raw.resolve(Path::new("c.toml")).unwrap_err().to_string();
            assert!(e.contains("c.toml") && e.contains(field), "{e}");
        };
        let mut r = raw.clone();
        r.sets[0].kind = ViewKind::Rectified;
        check(&r, "set[0].camera"); // F195 cannot be rectified
        let mut r = raw.clone();
        r.sets[0].kind = ViewKind::Pers;
        check(&r, "set[0].camera");
        let mut r = raw.clone();
        r.panoramas.split.val = 0.5;
        check(&r, "panoramas.split");
        let mut r = raw.clone();
        r.sets[0].name = "../up".into();
        check(&r, "set[0].name");
        let mut r = raw.clone();
        r.sets[0].camera = PathBuf::from("/nonexistent/cam.toml");
        check(&r, "/nonexistent/cam.toml");
        let mut r = raw.clone();
        r.panoramas.source = SourceKind::Stanford;
        check(&r, "panoramas.stanford_root");
        let e = RawSynthConfig::parse("seed = 1\nbogus = 2\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus") && e.contains("x.toml"), "{e}");
    }
}
