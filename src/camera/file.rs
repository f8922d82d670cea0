//! Camera files: flat TOML with named fields (`data/cameras/*.toml`), never positional arrays
//! (the one exception is a polynomial's coefficient list, in ascending powers).
//!
//! ```toml
//! model = "kannala-brandt"        # one of MODELS, see below
//! name = "F195"                   # optional, ignored
//! description = "..."             # optional, ignored
//! width = 1080                    # pixels
//! height = 960
//! fov_deg = 195.0                 # full field of view, degrees (fisheye models)
//! fx = 287.0                      # pixels
//! fy = 287.0
//! cx = 540.0                      # pixels, top-left pixel centre at 0
//! cy = 480.0
//! k1 = 3.37012024344156e-19       # kannala-brandt only, all four required
//! k2 = -3.543830680552053e-05
//! k3 = 9.999999999924497e-08
//! k4 = -6.883696004705416e-11
//! ```
//!
//! Fields per model (every one required unless marked optional):
//!
//! | `model` | fields besides `width`, `height` |
//! |---|---|
//! | `kannala-brandt` | `fov_deg fx fy cx cy k1 k2 k3 k4` |
//! | `pinhole` | `fx fy cx cy` (field of view derived) |
//! | `pinhole-radtan` | `fx fy cx cy k1 k2 p1 p2 k3` (OpenCV order and meaning; fov derived) |
//! | `double-sphere` | `fov_deg fx fy cx cy xi alpha` |
//! | `unified` | `fov_deg fx fy cx cy alpha` |
//! | `extended-unified` | `fov_deg fx fy cx cy alpha beta` |
//! | `scaramuzza` | `fov_deg cx cy c d e poly`, optional `inv_poly` (OCamCalib; `cx` is the column) |
//! | `equirectangular` | none |
//!
//! Reading goes text -> `toml::Table` (for `model`) -> `Raw*` (serde, `deny_unknown_fields`, so a
//! misspelt key is an error naming it) -> checked model. Checks: every float finite, `fx, fy > 0`,
//! `width, height > 0`, `0 < fov_deg < 360`; Kannala-Brandt: a polynomial that increases on
//! `[0, fov_deg / 2]`; radial-tangential: every pixel of the image border unprojects (the
//! distortion does not fold inside the image); double sphere: `xi in (-1, 1]`, `alpha in [0, 1]`;
//! unified: `alpha in [0, 1)`; extended unified: `alpha in [0, 1]`, `beta > 0`; Scaramuzza:
//! `a0 < 0`, `c - d e > 0`; every fisheye model: `fov_deg / 2` below the model's largest
//! projectable angle. Errors name the file and the field.
//!
//! [`to_toml`] writes the same format (used by `calibconv camera import`).

use std::path::Path;

use serde::Deserialize;

use super::{
    Camera, CameraModel, DoubleSphere, Equirectangular, ExtendedUnified, KannalaBrandt, Pinhole,
    PinholeRadTan, Scaramuzza, Unified,
};
use crate::error::{Error, Result};

/// The values of `model` this module reads.
pub const MODELS: [&str; 8] = [
    "kannala-brandt",
    "pinhole",
    "pinhole-radtan",
    "double-sphere",
    "unified",
    "extended-unified",
    "scaramuzza",
    "equirectangular",
];

/// Longest polynomial accepted for the Scaramuzza model (OCamCalib's `MAX_POL_LENGTH` is 64).
const MAX_POLY_LEN: usize = 64;

/// Pixels checked along each edge of a radial-tangential image for invertibility (plus the
/// corners): a fold narrower than 1/256 of an edge between two checked pixels is not realistic.
const BORDER_SAMPLES: usize = 256;

/// Reads and parses the camera file at `path`.
pub(super) fn load(path: &Path) -> Result<Camera> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse(&text, path)
}

/// Parses the text of a camera file; `path` only names the file in errors.
pub fn parse(text: &str, path: &Path) -> Result<Camera> {
    let table: toml::Table = toml::from_str(text).map_err(|e| toml_error(path, e))?;
    let known = || {
        MODELS
            .iter()
            .map(|m| format!("`{m}`"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let model = match table.get("model") {
        None => {
            return Err(camera_error(
                path,
                "model",
                format!("missing; expected one of {}", known()),
            ))
        }
        Some(toml::Value::String(model)) => model.as_str(),
        Some(other) => {
            return Err(camera_error(
                path,
                "model",
                format!("expected a string, one of {}, found {other}", known()),
            ))
        }
    };
    // Deserialise from the text, not the table, so that errors point at the line.
    fn raw<T: serde::de::DeserializeOwned>(text: &str, path: &Path) -> Result<T> {
        toml::from_str(text).map_err(|e| toml_error(path, e))
    }
    match model {
        "kannala-brandt" => raw::<RawKannalaBrandt>(text, path)?
            .resolve(path)
            .map(Camera::KannalaBrandt),
        "pinhole" => raw::<RawPinhole>(text, path)?
            .resolve(path)
            .map(Camera::Pinhole),
        "pinhole-radtan" => raw::<RawPinholeRadTan>(text, path)?
            .resolve(path)
            .map(Camera::PinholeRadTan),
        "double-sphere" => raw::<RawDoubleSphere>(text, path)?
            .resolve(path)
            .map(Camera::DoubleSphere),
        "unified" => raw::<RawUnified>(text, path)?
            .resolve(path)
            .map(Camera::Unified),
        "extended-unified" => raw::<RawExtendedUnified>(text, path)?
            .resolve(path)
            .map(Camera::ExtendedUnified),
        "scaramuzza" => raw::<RawScaramuzza>(text, path)?
            .resolve(path)
            .map(Camera::Scaramuzza),
        "equirectangular" => raw::<RawEquirectangular>(text, path)?
            .resolve(path)
            .map(Camera::Equirectangular),
        other => Err(camera_error(
            path,
            "model",
            format!("unknown model `{other}`; expected one of {}", known()),
        )),
    }
}

/// The text of a camera file for `camera`: `header` lines as `#` comments, then `name` and
/// `description` when given, then `model` and every field of the model by name. Floats are
/// written as the shortest text that reads back to the same `f64`, so [`parse`] returns
/// `camera` again.
pub fn to_toml(
    camera: &Camera,
    header: &[String],
    name: Option<&str>,
    description: Option<&str>,
) -> String {
    let mut out = String::new();
    for line in header {
        out.push_str(&format!("# {line}\n"));
    }
    let quote = |s: &str| toml::Value::String(s.to_string()).to_string();
    if let Some(name) = name {
        out.push_str(&format!("name = {}\n", quote(name)));
    }
    if let Some(description) = description {
        out.push_str(&format!("description = {}\n", quote(description)));
    }
    out.push_str(&format!("model = {}\n", quote(camera.model_name())));
    let [width, height] = camera.size();
    out.push_str(&format!("width = {width}\nheight = {height}\n"));
    let mut floats: Vec<(&str, f64)> = Vec::new();
    match camera {
        Camera::KannalaBrandt(m) => {
            floats.extend([("fov_deg", m.fov_deg), ("fx", m.fx), ("fy", m.fy)]);
            floats.extend([("cx", m.cx), ("cy", m.cy)]);
            floats.extend([
                ("k1", m.k[0]),
                ("k2", m.k[1]),
                ("k3", m.k[2]),
                ("k4", m.k[3]),
            ]);
        }
        Camera::Pinhole(m) => {
            floats.extend([("fx", m.fx), ("fy", m.fy), ("cx", m.cx), ("cy", m.cy)]);
        }
        Camera::PinholeRadTan(m) => {
            floats.extend([("fx", m.fx), ("fy", m.fy), ("cx", m.cx), ("cy", m.cy)]);
            floats.extend([
                ("k1", m.k[0]),
                ("k2", m.k[1]),
                ("p1", m.p[0]),
                ("p2", m.p[1]),
            ]);
            floats.push(("k3", m.k[2]));
        }
        Camera::DoubleSphere(m) => {
            floats.extend([("fov_deg", m.fov_deg), ("fx", m.fx), ("fy", m.fy)]);
            floats.extend([("cx", m.cx), ("cy", m.cy), ("xi", m.xi), ("alpha", m.alpha)]);
        }
        Camera::Unified(m) => {
            floats.extend([("fov_deg", m.fov_deg), ("fx", m.fx), ("fy", m.fy)]);
            floats.extend([("cx", m.cx), ("cy", m.cy), ("alpha", m.alpha)]);
        }
        Camera::ExtendedUnified(m) => {
            floats.extend([("fov_deg", m.fov_deg), ("fx", m.fx), ("fy", m.fy)]);
            floats.extend([
                ("cx", m.cx),
                ("cy", m.cy),
                ("alpha", m.alpha),
                ("beta", m.beta),
            ]);
        }
        Camera::Scaramuzza(m) => {
            floats.extend([("fov_deg", m.fov_deg), ("cx", m.cx), ("cy", m.cy)]);
            floats.extend([("c", m.c), ("d", m.d), ("e", m.e)]);
        }
        Camera::Equirectangular(_) => {}
    }
    for (key, value) in floats {
        out.push_str(&format!("{key} = {}\n", float(value)));
    }
    if let Camera::Scaramuzza(m) = camera {
        out.push_str(&format!("poly = {}\n", float_list(&m.poly)));
        if !m.inv_poly.is_empty() {
            out.push_str(&format!("inv_poly = {}\n", float_list(&m.inv_poly)));
        }
    }
    out
}

/// `{:?}` prints the shortest text that reads back to the same `f64` (`1.0`, `1e-5`, `-0.25`),
/// always a valid TOML float for finite values.
fn float(v: f64) -> String {
    format!("{v:?}")
}

fn float_list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|v| float(*v)).collect();
    format!("[{}]", items.join(", "))
}

/// A Kannala-Brandt camera file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawKannalaBrandt {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fov_deg: f64,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k1: f64,
    k2: f64,
    k3: f64,
    k4: f64,
}

impl RawKannalaBrandt {
    fn resolve(self, path: &Path) -> Result<KannalaBrandt> {
        check_finite(
            path,
            &[
                ("fov_deg", self.fov_deg),
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
                ("k1", self.k1),
                ("k2", self.k2),
                ("k3", self.k3),
                ("k4", self.k4),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        check_fov(path, self.fov_deg)?;
        let cam = KannalaBrandt::new(
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            [self.k1, self.k2, self.k3, self.k4],
            self.width,
            self.height,
            self.fov_deg,
        );
        let half_fov = self.fov_deg / 2.0;
        if !cam.is_monotonic_to(half_fov.to_radians()) {
            return Err(camera_error(
                path,
                "k1..k4",
                format!(
                    "d(theta) stops increasing at theta = {:.3} deg, before fov_deg/2 = {:.3} deg",
                    cam.theta_max().to_degrees(),
                    half_fov
                ),
            ));
        }
        Ok(cam)
    }
}

/// A pinhole camera file as written (its field of view is derived, not stored).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPinhole {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

impl RawPinhole {
    fn resolve(self, path: &Path) -> Result<Pinhole> {
        check_finite(
            path,
            &[
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        Ok(Pinhole {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width: self.width,
            height: self.height,
        })
    }
}

/// A pinhole camera with OpenCV radial-tangential distortion, as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPinholeRadTan {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k1: f64,
    k2: f64,
    p1: f64,
    p2: f64,
    k3: f64,
}

impl RawPinholeRadTan {
    fn resolve(self, path: &Path) -> Result<PinholeRadTan> {
        check_finite(
            path,
            &[
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
                ("k1", self.k1),
                ("k2", self.k2),
                ("p1", self.p1),
                ("p2", self.p2),
                ("k3", self.k3),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        let cam = PinholeRadTan::new(
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            [self.k1, self.k2, self.k3],
            [self.p1, self.p2],
            self.width,
            self.height,
        );
        // The outer pixel edges, BORDER_SAMPLES + 1 points per side (corners included).
        let (w, h) = (self.width as f64, self.height as f64);
        let border = (0..=BORDER_SAMPLES).flat_map(|i| {
            let t = i as f64 / BORDER_SAMPLES as f64;
            let (u, v) = (-0.5 + t * w, -0.5 + t * h);
            [[u, -0.5], [u, h - 0.5], [-0.5, v], [w - 0.5, v]]
        });
        for px in border {
            if cam.unproject(px).is_none() {
                return Err(camera_error(
                    path,
                    "k1, k2, p1, p2, k3",
                    format!(
                        "the distortion folds inside the image: pixel ({}, {}) has no inverse \
                         (the radial part stops increasing at r = {:.4} on the z = 1 plane)",
                        px[0],
                        px[1],
                        cam.r_max()
                    ),
                ));
            }
        }
        Ok(cam)
    }
}

/// A Double Sphere camera file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDoubleSphere {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fov_deg: f64,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    xi: f64,
    alpha: f64,
}

impl RawDoubleSphere {
    fn resolve(self, path: &Path) -> Result<DoubleSphere> {
        check_finite(
            path,
            &[
                ("fov_deg", self.fov_deg),
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
                ("xi", self.xi),
                ("alpha", self.alpha),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        check_fov(path, self.fov_deg)?;
        if !(self.xi > -1.0 && self.xi <= 1.0) {
            return Err(camera_error(
                path,
                "xi",
                format!("must be in (-1, 1], found {}", self.xi),
            ));
        }
        check_unit_interval(path, "alpha", self.alpha)?;
        let cam = DoubleSphere {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            xi: self.xi,
            alpha: self.alpha,
            width: self.width,
            height: self.height,
            fov_deg: self.fov_deg,
        };
        check_fov_in_domain(path, self.fov_deg, cam.theta_max(), "xi, alpha")?;
        Ok(cam)
    }
}

/// A Unified Camera Model file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawUnified {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fov_deg: f64,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    alpha: f64,
}

impl RawUnified {
    fn resolve(self, path: &Path) -> Result<Unified> {
        check_finite(
            path,
            &[
                ("fov_deg", self.fov_deg),
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
                ("alpha", self.alpha),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        check_fov(path, self.fov_deg)?;
        if !(self.alpha >= 0.0 && self.alpha < 1.0) {
            return Err(camera_error(
                path,
                "alpha",
                format!(
                    "must be in [0, 1) (alpha = 1 puts Mei's xi at infinity), found {}",
                    self.alpha
                ),
            ));
        }
        let cam = Unified {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            alpha: self.alpha,
            width: self.width,
            height: self.height,
            fov_deg: self.fov_deg,
        };
        check_fov_in_domain(path, self.fov_deg, cam.theta_max(), "alpha")?;
        Ok(cam)
    }
}

/// An Extended Unified Camera Model file as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawExtendedUnified {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fov_deg: f64,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    alpha: f64,
    beta: f64,
}

impl RawExtendedUnified {
    fn resolve(self, path: &Path) -> Result<ExtendedUnified> {
        check_finite(
            path,
            &[
                ("fov_deg", self.fov_deg),
                ("fx", self.fx),
                ("fy", self.fy),
                ("cx", self.cx),
                ("cy", self.cy),
                ("alpha", self.alpha),
                ("beta", self.beta),
            ],
        )?;
        check_intrinsics(path, self.fx, self.fy, self.width, self.height)?;
        check_fov(path, self.fov_deg)?;
        check_unit_interval(path, "alpha", self.alpha)?;
        if self.beta <= 0.0 {
            return Err(camera_error(
                path,
                "beta",
                format!("must be > 0, found {}", self.beta),
            ));
        }
        let cam = ExtendedUnified {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            alpha: self.alpha,
            beta: self.beta,
            width: self.width,
            height: self.height,
            fov_deg: self.fov_deg,
        };
        check_fov_in_domain(path, self.fov_deg, cam.theta_max(), "alpha, beta")?;
        Ok(cam)
    }
}

/// A Scaramuzza (OCamCalib) camera file as written. `cx` is the centre column (OCamCalib's
/// `yc`), `cy` the centre row (its `xc`).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScaramuzza {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
    fov_deg: f64,
    cx: f64,
    cy: f64,
    c: f64,
    d: f64,
    e: f64,
    poly: Vec<f64>,
    #[serde(default)]
    inv_poly: Vec<f64>,
}

impl RawScaramuzza {
    fn resolve(self, path: &Path) -> Result<Scaramuzza> {
        check_finite(
            path,
            &[
                ("fov_deg", self.fov_deg),
                ("cx", self.cx),
                ("cy", self.cy),
                ("c", self.c),
                ("d", self.d),
                ("e", self.e),
            ],
        )?;
        for (field, list) in [("poly", &self.poly), ("inv_poly", &self.inv_poly)] {
            if let Some((i, v)) = list.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(camera_error(
                    path,
                    field,
                    format!("coefficient {i} must be finite, found {v}"),
                ));
            }
            if list.len() > MAX_POLY_LEN {
                return Err(camera_error(
                    path,
                    field,
                    format!("{} coefficients, at most {MAX_POLY_LEN}", list.len()),
                ));
            }
        }
        match self.poly.first() {
            Some(&a0) if a0 < 0.0 => {}
            other => {
                return Err(camera_error(
                    path,
                    "poly",
                    format!(
                        "the first coefficient a0 must be negative (OCamCalib's cameras look \
                         along -z), found {other:?}"
                    ),
                ))
            }
        }
        let det = self.c - self.d * self.e;
        if det.is_nan() || det <= 0.0 {
            return Err(camera_error(
                path,
                "c, d, e",
                format!("the affine matrix [[c, d], [e, 1]] must have c - d e > 0, found {det}"),
            ));
        }
        for (field, n) in [("width", self.width), ("height", self.height)] {
            if n == 0 {
                return Err(camera_error(path, field, "must be > 0 px".to_string()));
            }
        }
        check_fov(path, self.fov_deg)?;
        let cam = Scaramuzza::new(
            self.poly,
            self.inv_poly,
            self.cx,
            self.cy,
            [self.c, self.d, self.e],
            self.width,
            self.height,
            self.fov_deg,
        );
        check_fov_in_domain(path, self.fov_deg, cam.theta_max(), "poly")?;
        Ok(cam)
    }
}

/// An equirectangular panorama file as written: only the size.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEquirectangular {
    #[allow(dead_code)] // read by `parse` from the table
    model: String,
    #[allow(dead_code)] // documentation only
    name: Option<String>,
    #[allow(dead_code)] // documentation only
    description: Option<String>,
    width: usize,
    height: usize,
}

impl RawEquirectangular {
    fn resolve(self, path: &Path) -> Result<Equirectangular> {
        for (field, n) in [("width", self.width), ("height", self.height)] {
            if n == 0 {
                return Err(camera_error(path, field, "must be > 0 px".to_string()));
            }
        }
        Ok(Equirectangular::new(self.width, self.height))
    }
}

fn camera_error(path: &Path, field: &str, message: String) -> Error {
    Error::Camera {
        path: path.to_path_buf(),
        field: field.to_string(),
        message,
    }
}

/// The toml error's text names the line, the column and the offending key.
fn toml_error(path: &Path, e: toml::de::Error) -> Error {
    Error::Toml {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    }
}

fn check_finite(path: &Path, fields: &[(&str, f64)]) -> Result<()> {
    match fields.iter().find(|(_, v)| !v.is_finite()) {
        Some((field, v)) => Err(camera_error(
            path,
            field,
            format!("must be finite, found {v}"),
        )),
        None => Ok(()),
    }
}

fn check_intrinsics(path: &Path, fx: f64, fy: f64, width: usize, height: usize) -> Result<()> {
    for (field, f) in [("fx", fx), ("fy", fy)] {
        if f <= 0.0 {
            return Err(camera_error(
                path,
                field,
                format!("focal length must be > 0 px, found {f}"),
            ));
        }
    }
    for (field, n) in [("width", width), ("height", height)] {
        if n == 0 {
            return Err(camera_error(path, field, "must be > 0 px".to_string()));
        }
    }
    Ok(())
}

fn check_fov(path: &Path, fov_deg: f64) -> Result<()> {
    if fov_deg > 0.0 && fov_deg < 360.0 {
        Ok(())
    } else {
        Err(camera_error(
            path,
            "fov_deg",
            format!("must be in (0, 360) degrees, found {fov_deg}"),
        ))
    }
}

fn check_unit_interval(path: &Path, field: &str, v: f64) -> Result<()> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err(camera_error(
            path,
            field,
            format!("must be in [0, 1], found {v}"),
        ))
    }
}

/// `fov_deg / 2` must be below the model's largest projectable angle `theta_max` (radians),
/// which `params` (the fields that set it) determine.
fn check_fov_in_domain(path: &Path, fov_deg: f64, theta_max: f64, params: &str) -> Result<()> {
    if (fov_deg / 2.0).to_radians() < theta_max {
        Ok(())
    } else {
        Err(camera_error(
            path,
            "fov_deg",
            format!(
                "fov_deg/2 = {:.3} deg, but with these {params} the model projects rays only up \
                 to {:.3} deg from the optical axis",
                fov_deg / 2.0,
                theta_max.to_degrees()
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::FRAC_PI_2;
    use std::path::PathBuf;

    use super::*;
    use crate::camera::{load, CameraModel, PixelConvention};

    /// Pixel round trips: the iterative inverses (Kannala-Brandt, radial-tangential, Scaramuzza)
    /// stop at quadratically shrinking steps below 1e-10 px or less, the closed forms are exact,
    /// so the error is round-off, ~1e-12 px; 1e-9 px is margin, not slack for a bug.
    const PX_TOL: f64 = 1e-9;
    /// Ray round trips in angle: round-off is ~1e-15 rad; 1e-9 rad is margin.
    const ANGLE_TOL: f64 = 1e-9;
    /// Central differences with h = 1e-6 on unit-scale rays: truncation ~1e-10, cancellation
    /// ~1e-16 * 1e3 px / 1e-6 = 1e-7 px; compared relative to fx / |ray| (~300..5000 px).
    const JAC_REL_TOL: f64 = 1e-6;
    const FD_STEP: f64 = 1e-6;
    /// The panorama's Jacobian grows like 1 / cos(latitude) and its third derivative like
    /// 1 / cos^3: closer than 0.05 rad to a pole central differences lose the accuracy above,
    /// so those rays are skipped by the sweep (the model's own tests cover them).
    const POLE_MARGIN: f64 = 0.05;
    /// Central differences across the panorama's seam jump by the image width: rays within
    /// 1e-3 rad (>> FD_STEP) of it are skipped.
    const SEAM_MARGIN: f64 = 1e-3;

    fn shipped(name: &str) -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("data/cameras")
            .join(name)
    }

    fn f195_text() -> String {
        std::fs::read_to_string(shipped("f195.toml")).unwrap()
    }

    fn bad(text: &str) -> Error {
        parse(text, Path::new("cams/bad.toml")).expect_err("should not parse")
    }

    fn field_of(e: &Error) -> &str {
        match e {
            Error::Camera { field, .. } => field,
            other => panic!("expected Error::Camera, got {other:?}"),
        }
    }

    fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
        let cross = [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ];
        let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        cross[0].hypot(cross[1]).hypot(cross[2]).atan2(dot)
    }

    #[test]
    fn shipped_files_hold_the_documented_values() {
        let f195 = load(shipped("f195.toml")).unwrap();
        assert_eq!(
            f195,
            Camera::KannalaBrandt(KannalaBrandt::new(
                287.0,
                287.0,
                540.0,
                480.0,
                [
                    3.37012024344156e-19,
                    -3.543830680552053e-05,
                    9.999999999924497e-08,
                    -6.883696004705416e-11,
                ],
                1080,
                960,
                195.0,
            ))
        );
        let f165 = load(shipped("f165.toml")).unwrap();
        assert_eq!(
            f165,
            Camera::KannalaBrandt(KannalaBrandt::new(
                326.0, 326.0, 540.0, 480.0, [0.0; 4], 1080, 960, 165.0
            ))
        );
        let Camera::KannalaBrandt(kb) = &f165 else {
            unreachable!()
        };
        // The 165 degree circle stays inside the image height.
        let r = kb.fx * kb.distort(82.5f64.to_radians());
        assert!(r > 460.0 && r < 480.0, "{r}");
        let pers = load(shipped("pers.toml")).unwrap();
        assert_eq!(
            pers,
            Camera::Pinhole(Pinhole {
                fx: 540.0,
                fy: 540.0,
                cx: 540.0,
                cy: 480.0,
                width: 1080,
                height: 960
            })
        );
        assert!((pers.fov() - FRAC_PI_2).abs() < 1e-15);
        // EuRoC MAV cam0 (sensor.yaml, Kalibr pinhole-radtan, k3 = 0).
        assert_eq!(
            load(shipped("radtan_example.toml")).unwrap(),
            Camera::PinholeRadTan(PinholeRadTan::new(
                458.654,
                457.296,
                367.215,
                248.375,
                [-0.28340811, 0.07395907, 0.0],
                [0.00019359, 1.76187114e-05],
                752,
                480
            ))
        );
        assert_eq!(
            load(shipped("equirect.toml")).unwrap(),
            Camera::Equirectangular(Equirectangular::new(1024, 512))
        );
        assert_eq!(
            load(shipped("ds_example.toml")).unwrap(),
            Camera::DoubleSphere(DoubleSphere {
                fx: 158.28,
                fy: 158.27,
                cx: 254.96,
                cy: 256.88,
                xi: -0.172,
                alpha: 0.593,
                width: 512,
                height: 512,
                fov_deg: 153.4,
            })
        );
    }

    /// Every camera file in `data/cameras/`, sorted by name.
    fn shipped_cameras() -> Vec<(String, Camera)> {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/cameras");
        let mut names: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".toml"))
            .collect();
        names.sort();
        names
            .into_iter()
            .map(|n| {
                let cam = load(shipped(&n)).unwrap_or_else(|e| panic!("{n}: {e}"));
                (n, cam)
            })
            .collect()
    }

    /// The pixel the optical axis (`+z`) projects to.
    fn principal_point(cam: &Camera) -> [f64; 2] {
        match cam {
            Camera::KannalaBrandt(m) => [m.cx, m.cy],
            Camera::Pinhole(m) => [m.cx, m.cy],
            Camera::PinholeRadTan(m) => [m.cx, m.cy],
            Camera::DoubleSphere(m) => [m.cx, m.cy],
            Camera::Unified(m) => [m.cx, m.cy],
            Camera::ExtendedUnified(m) => [m.cx, m.cy],
            Camera::Scaramuzza(m) => [m.cx, m.cy],
            Camera::Equirectangular(m) => [m.cu, m.cv],
        }
    }

    /// Pixels per radian near the axis (the Jacobian's scale for a unit ray).
    fn pixel_scale(cam: &Camera) -> f64 {
        match cam {
            Camera::KannalaBrandt(m) => m.fx,
            Camera::Pinhole(m) => m.fx,
            Camera::PinholeRadTan(m) => m.fx,
            Camera::DoubleSphere(m) => m.fx,
            Camera::Unified(m) => m.fx,
            Camera::ExtendedUnified(m) => m.fx,
            Camera::Scaramuzza(m) => -m.poly[0],
            Camera::Equirectangular(m) => m.fu,
        }
    }

    /// The sweep over every shipped camera (every file in `data/cameras/`, which holds at least
    /// one camera of each model): pixel and ray round trips at several depths, the principal
    /// point, rays past 90 degrees where the model allows them, outside the domain -> None,
    /// Jacobian vs central differences, rescaling.
    #[test]
    fn every_shipped_camera_sweep() {
        let cameras = shipped_cameras();
        for model in MODELS {
            assert!(
                cameras.iter().any(|(_, c)| c.model_name() == model),
                "no camera file of model `{model}` in data/cameras: the sweep would skip it"
            );
        }
        for (name, cam) in &cameras {
            sweep(name, cam);
        }
    }

    fn sweep(name: &str, cam: &Camera) {
        let [w, h] = cam.size();
        let [cx, cy] = principal_point(cam);
        let scale = pixel_scale(cam);

        // project(unproject(px)) over the whole image, every 4 px plus the outer pixel edges.
        let us = (0..w)
            .step_by(4)
            .map(|u| u as f64)
            .chain([-0.5, w as f64 - 0.5]);
        let mut checked = 0;
        for u in us {
            let vs = (0..h)
                .step_by(4)
                .map(|v| v as f64)
                .chain([-0.5, h as f64 - 0.5]);
            for v in vs {
                let ray = cam
                    .unproject([u, v])
                    .unwrap_or_else(|| panic!("{name} {u} {v}"));
                assert!((ray[0].hypot(ray[1]).hypot(ray[2]) - 1.0).abs() < 1e-15);
                for len in [0.1, 1.0, 10.0] {
                    let px = cam.project(ray.map(|c| c * len)).unwrap();
                    let err = (px[0] - u).hypot(px[1] - v);
                    assert!(err < PX_TOL, "{name} ({u}, {v}) x{len}: {err} px");
                }
                checked += 1;
            }
        }
        assert!(
            checked >= w.div_ceil(4) * h.div_ceil(4),
            "{name}: {checked}"
        );

        // unproject(project(ray)) for rays over the field of view (past 90 deg for fisheyes, the
        // whole sphere for the panorama).
        let half_fov = cam.fov() / 2.0;
        for i in 0..=60 {
            let theta = half_fov * i as f64 / 60.0;
            for j in 0..36 {
                let phi = std::f64::consts::TAU * j as f64 / 36.0;
                let unit = [
                    theta.sin() * phi.cos(),
                    theta.sin() * phi.sin(),
                    theta.cos(),
                ];
                for len in [0.1, 1.0, 10.0] {
                    let ray = unit.map(|c| c * len);
                    let px = cam.project(ray).unwrap();
                    let back = cam.unproject(px).unwrap();
                    let err = angle(ray, back);
                    assert!(err < ANGLE_TOL, "{name} theta {theta} phi {phi}: {err} rad");

                    // Jacobian vs central differences, except where the panorama's projection
                    // is not differentiable: near the poles and across the seam.
                    let pole_or_seam = cam.wraps_horizontally()
                        && (unit[0].hypot(unit[2]) < POLE_MARGIN
                            || unit[0].atan2(unit[2]).abs() > std::f64::consts::PI - SEAM_MARGIN);
                    if theta < half_fov && !pole_or_seam {
                        let jac = cam.project_jacobian(ray).unwrap();
                        for k in 0..3 {
                            let (mut p, mut m) = (ray, ray);
                            p[k] += FD_STEP * len;
                            m[k] -= FD_STEP * len;
                            let (pp, pm) = (cam.project(p).unwrap(), cam.project(m).unwrap());
                            for r in 0..2 {
                                let fd = (pp[r] - pm[r]) / (2.0 * FD_STEP * len);
                                assert!(
                                    (fd - jac[r][k]).abs() < JAC_REL_TOL * scale / len,
                                    "{name} theta {theta} phi {phi} len {len} [{r}][{k}]: \
                                     {fd} vs {}",
                                    jac[r][k]
                                );
                            }
                        }
                    }
                }
            }
        }

        // The principal point is the optical axis.
        assert_eq!(cam.unproject([cx, cy]), Some([0.0, 0.0, 1.0]), "{name}");
        assert_eq!(cam.project([0.0, 0.0, 4.0]), Some([cx, cy]), "{name}");

        // Rays past 90 degrees where the model allows them; outside the domain -> None.
        let ray_at = |deg: f64| {
            let t = deg.to_radians();
            [t.sin(), 0.0, t.cos()]
        };
        let past = cam.project(ray_at(100.0));
        assert_eq!(cam.project([0.0, 0.0, 0.0]), None, "{name}");
        assert_eq!(cam.project([f64::NAN, 0.0, 1.0]), None, "{name}");
        let behind = cam.project([0.0, 0.0, -1.0]);
        let theta_max = match cam {
            Camera::KannalaBrandt(m) => {
                let edge = m.fx * m.distort(m.theta_max());
                assert_eq!(cam.unproject([cx + 1.01 * edge, cy]), None, "{name}");
                Some(m.theta_max())
            }
            Camera::Pinhole(_) | Camera::PinholeRadTan(_) => {
                assert_eq!(cam.project([0.3, 0.1, -1.0]), None, "{name}");
                assert_eq!(cam.project([1.0, 0.0, 0.0]), None, "{name}");
                None
            }
            Camera::DoubleSphere(m) => Some(m.theta_max()),
            Camera::Unified(m) => Some(m.theta_max()),
            Camera::ExtendedUnified(m) => Some(m.theta_max()),
            Camera::Scaramuzza(m) => {
                assert_eq!(cam.unproject([cx + 1.01 * m.rho_max(), cy]), None, "{name}");
                Some(m.theta_max())
            }
            Camera::Equirectangular(_) => {
                assert!(
                    behind.is_some() && past.is_some(),
                    "{name}: the whole sphere"
                );
                assert_eq!(cam.unproject([cx, -0.6]), None, "{name}: beyond the pole");
                None
            }
        };
        match theta_max {
            Some(tm) => {
                assert_eq!(behind, None, "{name}");
                assert!(tm > 100f64.to_radians(), "{name}: {} deg", tm.to_degrees());
                assert!(past.is_some(), "{name}");
                if tm < std::f64::consts::PI - 1e-3 {
                    assert_eq!(
                        cam.project(ray_at((tm + 1e-3).to_degrees())),
                        None,
                        "{name}"
                    );
                }
            }
            None if !cam.wraps_horizontally() => {
                assert_eq!((past, behind), (None, None), "{name}");
            }
            None => {}
        }

        // Rescaling keeps the model and is undone by the inverse scale.
        let half = cam.rescaled([0.5, 0.5], PixelConvention::HalfPixel);
        assert_eq!(half.size(), [w / 2, h / 2]);
        assert_eq!(half.model_name(), cam.model_name());
        assert_eq!(&half.rescaled([2.0, 2.0], PixelConvention::HalfPixel), cam);
    }

    #[test]
    fn name_and_description_are_optional() {
        let text = f195_text();
        let stripped: String = text
            .lines()
            .filter(|l| !l.starts_with("name") && !l.starts_with("description"))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(
            parse(&stripped, Path::new("a.toml")).unwrap(),
            parse(&text, Path::new("b.toml")).unwrap()
        );
    }

    #[test]
    fn misspelt_key_names_the_key_and_the_file() {
        let e = bad(&f195_text().replace("fx = 287.0", "fxx = 287.0"));
        assert!(matches!(e, Error::Toml { .. }), "{e:?}");
        let msg = e.to_string();
        assert!(
            msg.contains("fxx") && msg.contains("cams/bad.toml"),
            "{msg}"
        );
        // A key that belongs to the other model is unknown too.
        let pers = std::fs::read_to_string(shipped("pers.toml")).unwrap();
        let msg = bad(&format!("{pers}fov_deg = 90.0\n")).to_string();
        assert!(msg.contains("fov_deg"), "{msg}");
        // A missing key.
        let msg = bad(&f195_text().replace("k3 =", "# k3 =")).to_string();
        assert!(msg.contains("k3"), "{msg}");
    }

    #[test]
    fn non_finite_focal_names_the_field() {
        let e = bad(&f195_text().replace("fx = 287.0", "fx = nan"));
        assert_eq!(field_of(&e), "fx");
        assert!(e.to_string().contains("cams/bad.toml"), "{e}");
        let e = bad(&f195_text().replace("k2 = -3.543830680552053e-05", "k2 = inf"));
        assert_eq!(field_of(&e), "k2");
    }

    #[test]
    fn non_positive_focal_and_empty_image_are_rejected() {
        assert_eq!(
            field_of(&bad(&f195_text().replace("fx = 287.0", "fx = 0.0"))),
            "fx"
        );
        assert_eq!(
            field_of(&bad(&f195_text().replace("fy = 287.0", "fy = -287.0"))),
            "fy"
        );
        assert_eq!(
            field_of(&bad(&f195_text().replace("width = 1080", "width = 0"))),
            "width"
        );
        let pers = std::fs::read_to_string(shipped("pers.toml")).unwrap();
        assert_eq!(
            field_of(&bad(&pers.replace("fx = 540.0", "fx = -1.0"))),
            "fx"
        );
    }

    #[test]
    fn fov_out_of_range_is_rejected() {
        for fov in ["0.0", "360.0", "-10.0"] {
            let e = bad(&f195_text().replace("fov_deg = 195.0", &format!("fov_deg = {fov}")));
            assert_eq!(field_of(&e), "fov_deg");
        }
    }

    #[test]
    fn unknown_or_missing_model_lists_the_known_models() {
        for text in [
            f195_text().replace("\"kannala-brandt\"", "\"fisheye\""),
            f195_text().replace("model =", "# model ="),
            f195_text().replace("\"kannala-brandt\"", "3"),
        ] {
            let e = bad(&text);
            assert_eq!(field_of(&e), "model");
            let msg = e.to_string();
            assert!(
                msg.contains("kannala-brandt") && msg.contains("pinhole"),
                "{msg}"
            );
        }
    }

    #[test]
    fn polynomial_folding_inside_the_declared_fov_is_rejected() {
        // d' = 1 - 1.5 theta^2 + ... vanishes near 46.8 deg, long before 97.5 deg.
        let text = f195_text().replace("k1 = 3.37012024344156e-19", "k1 = -0.5");
        let e = bad(&text);
        assert_eq!(field_of(&e), "k1..k4");
        let msg = e.to_string();
        assert!(
            msg.contains("stops increasing") && msg.contains("97.500"),
            "{msg}"
        );
        // The same polynomial is fine for a 90 degree lens.
        let ok = text.replace("fov_deg = 195.0", "fov_deg = 90.0");
        assert!(parse(&ok, Path::new("ok.toml")).is_ok());
    }

    #[test]
    fn missing_file_names_the_path() {
        let path = Path::new("/nonexistent/dir/camera.toml");
        let e = load(path).unwrap_err();
        assert!(matches!(e, Error::Io { .. }), "{e:?}");
        assert!(
            e.to_string().contains("/nonexistent/dir/camera.toml"),
            "{e}"
        );
    }

    #[test]
    fn syntax_error_is_a_toml_error() {
        let e = bad("model = \"pinhole\"\nfx = \n");
        assert!(matches!(e, Error::Toml { .. }), "{e:?}");
    }

    #[test]
    fn to_toml_round_trips_every_shipped_camera() {
        for (name, cam) in shipped_cameras() {
            let header = vec![format!("written from {name}"), "second line".to_string()];
            let text = to_toml(&cam, &header, Some("N \"quoted\""), Some("a description"));
            assert!(text.starts_with("# written from"), "{text}");
            let back = parse(&text, Path::new("written.toml"))
                .unwrap_or_else(|e| panic!("{name}: {e}\n{text}"));
            assert_eq!(back, cam, "{name}:\n{text}");
        }
        // Awkward floats come back bit for bit.
        let cam = Camera::KannalaBrandt(KannalaBrandt::new(
            0.1 + 0.2,
            1e300,
            -0.0,
            5e-324,
            [1.0 / 3.0, -2.5e-17, 0.0, 0.0],
            3,
            4,
            179.999_999_999_999_97,
        ));
        let text = to_toml(&cam, &[], None, None);
        assert_eq!(parse(&text, Path::new("w.toml")).unwrap(), cam, "{text}");
    }

    fn shipped_text(name: &str) -> String {
        std::fs::read_to_string(shipped(name)).unwrap()
    }

    #[test]
    fn new_models_check_their_parameters_by_field() {
        let ds = shipped_text("ds_example.toml");
        assert_eq!(
            field_of(&bad(&ds.replace("xi = -0.172", "xi = -1.0"))),
            "xi"
        );
        assert_eq!(field_of(&bad(&ds.replace("xi = -0.172", "xi = 1.5"))), "xi");
        assert_eq!(
            field_of(&bad(&ds.replace("alpha = 0.593", "alpha = 1.2"))),
            "alpha"
        );
        assert_eq!(field_of(&bad(&ds.replace("fx = 158.28", "fx = nan"))), "fx");
        // theta_max is ~125.3 deg for these xi, alpha: a 260 degree lens does not fit.
        let e = bad(&ds.replace("fov_deg = 153.4", "fov_deg = 260.0"));
        assert_eq!(field_of(&e), "fov_deg");
        assert!(e.to_string().contains("xi, alpha"), "{e}");

        let ucm = shipped_text("ucm_example.toml");
        assert_eq!(
            field_of(&bad(&ucm.replace("alpha = 0.48", "alpha = 1.0"))),
            "alpha"
        );
        assert_eq!(
            field_of(&bad(&ucm.replace("alpha = 0.48", "alpha = -0.1"))),
            "alpha"
        );

        let eucm = shipped_text("eucm_example.toml");
        assert_eq!(
            field_of(&bad(&eucm.replace("beta = 1.2", "beta = 0.0"))),
            "beta"
        );
        assert_eq!(
            field_of(&bad(&eucm.replace("alpha = 0.45", "alpha = 2.0"))),
            "alpha"
        );

        let ocam = shipped_text("ocam_example.toml");
        assert_eq!(field_of(&bad(&ocam.replace("[-181.0,", "[181.0,"))), "poly");
        assert_eq!(
            field_of(&bad(&ocam.replace("c = 1.0003", "c = -1.0"))),
            "c, d, e"
        );
        // rho f' - f = 181 + 0.01 rho^2 - 2e-4 rho^3 vanishes near rho = 117 px (theta ~ 30 deg).
        let folding = ocam
            .lines()
            .map(|l| match l.starts_with("poly") {
                true => "poly = [-181.0, 0.0, 0.01, -1e-4]\n".to_string(),
                false => format!("{l}\n"),
            })
            .collect::<String>();
        let e = bad(&folding);
        assert_eq!(field_of(&e), "fov_deg");
        assert!(e.to_string().contains("poly"), "{e}");
        let e = bad(&ocam.replace("[-181.0,", "[-181.0, inf,"));
        assert_eq!(field_of(&e), "poly");
        // inv_poly is optional.
        let stripped: String = ocam
            .lines()
            .filter(|l| !l.starts_with("inv_poly"))
            .map(|l| format!("{l}\n"))
            .collect();
        let Camera::Scaramuzza(m) = parse(&stripped, Path::new("o.toml")).unwrap() else {
            panic!("model changed");
        };
        assert!(m.inv_poly.is_empty());

        let eq = shipped_text("equirect.toml");
        assert_eq!(
            field_of(&bad(&eq.replace("width = 1024", "width = 0"))),
            "width"
        );
        let msg = bad(&format!("{eq}fov_deg = 360.0\n")).to_string();
        assert!(msg.contains("fov_deg"), "{msg}");
    }

    #[test]
    fn radtan_folding_inside_the_image_is_rejected() {
        // k1 = -0.5 folds at r = sqrt(2/3) = 0.816 on the z = 1 plane; the EuRoC image corner
        // is at r ~ 0.98, so the distortion folds inside the image.
        let text = shipped_text("radtan_example.toml")
            .replace("k1 = -0.28340811", "k1 = -0.5")
            .replace("k2 = 0.07395907", "k2 = 0.0");
        let e = bad(&text);
        assert_eq!(field_of(&e), "k1, k2, p1, p2, k3");
        assert!(e.to_string().contains("folds inside the image"), "{e}");
    }
}
