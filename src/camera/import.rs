//! Calibrations of other tools as cameras of this crate (`calibconv camera import`).
//!
//! | `--from` | file | models read |
//! |---|---|---|
//! | `kalibr` | camchain YAML (`camN:` blocks) | `pinhole-equi`, `pinhole-radtan`, `pinhole-none`, `ds-none`, `eucm-none`, `omni-none` (and `omni-radtan` with zero coefficients) |
//! | `opencv` | `cv::FileStorage` YAML (`%YAML:1.0`, `!!opencv-matrix`) or JSON, or plain YAML / JSON | fisheye (`K`, `D` = k1..k4) and standard (`D` = k1 k2 p1 p2 (k3), longer `D` only with zero extra terms) |
//! | `basalt` | calibration JSON (`value0.intrinsics[N]`) | `kb4`, `ds`, `eucm`, `ucm`, `pinhole` |
//! | `colmap` | `cameras.txt` | `OPENCV_FISHEYE`, `OPENCV`, `FULL_OPENCV` (zero k4..k6), `PINHOLE`, `SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL` |
//! | `ocamcalib` | `calib_results.txt` | Scaramuzza's model |
//!
//! Anything else (Kalibr `pinhole-fov`, Basalt `pinhole-radtan8`, COLMAP `FOV`, OpenCV's
//! rational model, ...) is an error naming the model.
//!
//! Conventions converted on the way in (all else is copied as is):
//! - COLMAP puts the centre of the top-left pixel at `(0.5, 0.5)`; this crate (like OpenCV,
//!   Kalibr, Basalt and OCamCalib's C export) at `(0, 0)`: COLMAP's `cx`, `cy` move by -0.5 px.
//! - Kalibr's `omni` is Mei's unified model `u = fu x / (z + xi d) + pu`; it is the crate's
//!   `unified` model with `alpha = xi / (1 + xi)` and `fx = fu / (1 + xi)` (same for `fy`).
//! - OCamCalib's centre is "row, column": `xc` becomes `cy`, `yc` becomes `cx`.
//! - Kalibr `pinhole-radtan` and OpenCV 4-coefficient standard distortion have `k3 = 0`.
//!
//! The field of view of the fisheye models (`fov_deg`) is rarely in the source file. Unless
//! given (`--fov-deg`), it is the angle the image **width** spans on the principal row: the
//! angle to the optical axis of the left pixel edge `(-0.5, cy)` plus that of the right one
//! `(width - 0.5, cy)`. For a lens whose image circle is narrower than the sensor that is more
//! than the lens sees (pass the lens's `--fov-deg` then); it is an error when an edge lies outside
//! the model's domain. Pinhole models derive their field of view and take no `--fov-deg`.
//!
//! JSON numbers are read exactly (serde_json's `float_roundtrip`), YAML numbers by Rust's own
//! float parser, so coefficients reach the camera file bit for bit.
//!
//! Every imported camera is built by its model's validating constructor, which the camera-file
//! reader calls too, so it is exactly what the written file will read back as.

use std::path::Path;

use serde_json::Value;

use super::geometry::angle_to_axis;
use super::{
    Camera, CameraModel, DoubleSphere, ExtendedUnified, Intrinsics, Invalid, KannalaBrandt,
    Pinhole, PinholeRadTan, Scaramuzza, Unified,
};
use crate::error::{Error, Result};

/// The source tools `calibconv camera import --from` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// Kalibr camchain YAML.
    Kalibr,
    /// OpenCV calibration (`cv::FileStorage` YAML / JSON, or plain YAML / JSON).
    OpenCv,
    /// Basalt calibration JSON.
    Basalt,
    /// COLMAP `cameras.txt`.
    Colmap,
    /// OCamCalib `calib_results.txt`.
    OcamCalib,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "kalibr" => Ok(Format::Kalibr),
            "opencv" => Ok(Format::OpenCv),
            "basalt" => Ok(Format::Basalt),
            "colmap" => Ok(Format::Colmap),
            "ocamcalib" => Ok(Format::OcamCalib),
            other => Err(format!(
                "unknown format `{other}` (expected kalibr, opencv, basalt, colmap or ocamcalib)"
            )),
        }
    }
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Format::Kalibr => "kalibr",
            Format::OpenCv => "opencv",
            Format::Basalt => "basalt",
            Format::Colmap => "colmap",
            Format::OcamCalib => "ocamcalib",
        })
    }
}

/// Which of OpenCV's two camera models an OpenCV file holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OpenCvModel {
    /// `cv::fisheye` (Kannala-Brandt, `D` = k1..k4).
    Fisheye,
    /// The standard pinhole model with radial-tangential distortion.
    Standard,
}

impl std::str::FromStr for OpenCvModel {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "fisheye" => Ok(OpenCvModel::Fisheye),
            "standard" => Ok(OpenCvModel::Standard),
            other => Err(format!(
                "unknown OpenCV model `{other}` (expected fisheye or standard)"
            )),
        }
    }
}

/// Choices the source file may leave open.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImportOptions {
    /// Which camera of a multi-camera file: Kalibr `camN`, Basalt `intrinsics[N]` (default 0),
    /// COLMAP `CAMERA_ID` (default: the first line).
    pub camera: Option<usize>,
    /// Full field of view in degrees, for the fisheye models (default: see the module docs).
    pub fov_deg: Option<f64>,
    /// OpenCV only: the model, when the file does not say (4 coefficients fit both).
    pub opencv_model: Option<OpenCvModel>,
}

/// Where an imported camera's `fov_deg` came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FovSource {
    /// `--fov-deg`.
    Given,
    /// The angle spanned by the image width on the principal row.
    ImageWidth,
    /// A pinhole model: the field of view follows from the intrinsics.
    Derived,
}

/// An imported camera and what the conversion did.
#[derive(Clone, Debug, PartialEq)]
pub struct Imported {
    /// The camera, checked like a camera file.
    pub camera: Camera,
    /// What was read, e.g. "kalibr cam0 (pinhole-equi)".
    pub source: String,
    /// Where `fov_deg` came from.
    pub fov: FovSource,
    /// One line per convention converted or value chosen, for the written file's header.
    pub notes: Vec<String>,
}

/// Reads `path` as a calibration file of `format`.
pub fn import_file(format: Format, path: &Path, options: &ImportOptions) -> Result<Imported> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    import_text(format, &text, path, options)
}

/// Parses `text` as a calibration file of `format`; `path` names the file in errors.
pub fn import_text(
    format: Format,
    text: &str,
    path: &Path,
    options: &ImportOptions,
) -> Result<Imported> {
    if options.camera.is_some() && matches!(format, Format::OpenCv | Format::OcamCalib) {
        return Err(format_error(
            path,
            format!("--camera does not apply to {format} files (they hold one camera)"),
        ));
    }
    if options.opencv_model.is_some() && format != Format::OpenCv {
        return Err(format_error(
            path,
            "--opencv-model applies to opencv files only".to_string(),
        ));
    }
    let parsed = match format {
        Format::Kalibr => kalibr(text, path, options)?,
        Format::OpenCv => opencv(text, path, options)?,
        Format::Basalt => basalt(text, path, options)?,
        Format::Colmap => colmap(text, path, options)?,
        Format::OcamCalib => ocamcalib(text, path)?,
    };
    finish(parsed, path, options)
}

/// Intrinsics read from a source file, before the field of view is chosen.
#[derive(Clone, Debug)]
enum Model {
    KannalaBrandt {
        f: [f64; 4],
        k: [f64; 4],
    },
    Pinhole {
        f: [f64; 4],
    },
    RadTan {
        f: [f64; 4],
        k: [f64; 3],
        p: [f64; 2],
    },
    DoubleSphere {
        f: [f64; 4],
        xi: f64,
        alpha: f64,
    },
    Unified {
        f: [f64; 4],
        alpha: f64,
    },
    ExtendedUnified {
        f: [f64; 4],
        alpha: f64,
        beta: f64,
    },
    Scaramuzza {
        poly: Vec<f64>,
        inv_poly: Vec<f64>,
        centre: [f64; 2],
        cde: [f64; 3],
    },
}

/// What a reader found: the model (`f` = `[fx, fy, cx, cy]`), the image size, a description.
struct Parsed {
    model: Model,
    size: [usize; 2],
    source: String,
    notes: Vec<String>,
}

/// The camera for `fov_deg` (ignored by the pinhole models), through the models' validating
/// constructors: exactly what the written camera file will read back as.
fn build(model: &Model, size: [usize; 2], fov_deg: f64) -> std::result::Result<Camera, Invalid> {
    let intrinsics = |f: [f64; 4]| Intrinsics::from_parts(f, size);
    Ok(match model.clone() {
        Model::KannalaBrandt { f, k } => {
            Camera::KannalaBrandt(KannalaBrandt::new(intrinsics(f), k, fov_deg)?)
        }
        Model::Pinhole { f } => Camera::Pinhole(Pinhole::new(intrinsics(f))?),
        Model::RadTan { f, k, p } => {
            Camera::PinholeRadTan(PinholeRadTan::new(intrinsics(f), k, p)?)
        }
        Model::DoubleSphere { f, xi, alpha } => {
            Camera::DoubleSphere(DoubleSphere::new(intrinsics(f), xi, alpha, fov_deg)?)
        }
        Model::Unified { f, alpha } => {
            Camera::Unified(Unified::new(intrinsics(f), alpha, fov_deg)?)
        }
        Model::ExtendedUnified { f, alpha, beta } => {
            Camera::ExtendedUnified(ExtendedUnified::new(intrinsics(f), alpha, beta, fov_deg)?)
        }
        Model::Scaramuzza {
            poly,
            inv_poly,
            centre,
            cde,
        } => Camera::Scaramuzza(Scaramuzza::new(poly, inv_poly, centre, cde, size, fov_deg)?),
    })
}

/// A fisheye camera without the checks, to probe the model's domain before `fov_deg` is chosen
/// (the domain does not depend on it); `None` for the pinhole models, which derive theirs.
fn probe(model: &Model, size: [usize; 2]) -> Option<Camera> {
    let intrinsics = |f: [f64; 4]| Intrinsics::from_parts(f, size);
    let fov_deg = 180.0;
    Some(match model.clone() {
        Model::Pinhole { .. } | Model::RadTan { .. } => return None,
        Model::KannalaBrandt { f, k } => {
            Camera::KannalaBrandt(KannalaBrandt::unchecked(intrinsics(f), k, fov_deg))
        }
        Model::DoubleSphere { f, xi, alpha } => {
            Camera::DoubleSphere(DoubleSphere::unchecked(intrinsics(f), xi, alpha, fov_deg))
        }
        Model::Unified { f, alpha } => {
            Camera::Unified(Unified::unchecked(intrinsics(f), alpha, fov_deg))
        }
        Model::ExtendedUnified { f, alpha, beta } => Camera::ExtendedUnified(
            ExtendedUnified::unchecked(intrinsics(f), alpha, beta, fov_deg),
        ),
        Model::Scaramuzza {
            poly,
            inv_poly,
            centre,
            cde,
        } => Camera::Scaramuzza(Scaramuzza::unchecked(
            poly, inv_poly, centre, cde, size, fov_deg,
        )),
    })
}

/// Rounds the width-derived field of view down to 1e-3 deg (readable, and never past an edge).
const FOV_DECIMALS: f64 = 1e3;

/// Chooses `fov_deg` (module docs) and checks the camera like a camera file.
fn finish(parsed: Parsed, path: &Path, options: &ImportOptions) -> Result<Imported> {
    let Parsed {
        model,
        size,
        source,
        mut notes,
    } = parsed;
    let pinhole = matches!(model, Model::Pinhole { .. } | Model::RadTan { .. });
    let fov = if pinhole {
        if options.fov_deg.is_some() {
            return Err(format_error(
                path,
                format!(
                    "--fov-deg does not apply to {source}: a pinhole camera's field of view \
                     follows from its focal length and width"
                ),
            ));
        }
        FovSource::Derived
    } else if options.fov_deg.is_some() {
        FovSource::Given
    } else {
        FovSource::ImageWidth
    };
    let fov_deg = match (fov, options.fov_deg) {
        (FovSource::Given, Some(f)) => {
            notes.push(format!(
                "fov_deg: {f} deg, given on the command line (--fov-deg)"
            ));
            f
        }
        (FovSource::ImageWidth, _) => {
            let Some(probe) = probe(&model, size) else {
                unreachable!("pinhole models derive their field of view")
            };
            let [w, _] = size;
            let cy = principal_row(&probe);
            let mut total = 0.0;
            for u in [-0.5, w as f64 - 0.5] {
                let ray = probe.unproject([u, cy]).ok_or_else(|| {
                    camera_error(
                        path,
                        "fov_deg",
                        format!(
                            "the image edge ({u}, {cy}) lies outside the {} model's domain, so \
                             the field of view cannot be taken from the image width: pass \
                             --fov-deg",
                            probe.model_name()
                        ),
                    )
                })?;
                total += angle_to_axis(ray).to_degrees();
            }
            let fov = (total * FOV_DECIMALS).floor() / FOV_DECIMALS;
            notes.push(format!(
                "fov_deg: {fov} deg, the angle the image width spans on the principal row (the \
                 source does not give it; import with --fov-deg to set the lens's own)"
            ));
            fov
        }
        _ => 180.0, // unused by pinhole models
    };
    let camera = build(&model, size, fov_deg).map_err(|e| e.in_file(path))?;
    Ok(Imported {
        camera,
        source,
        fov,
        notes,
    })
}

/// The principal row of a camera built by [`build`].
fn principal_row(camera: &Camera) -> f64 {
    match camera {
        Camera::KannalaBrandt(m) => m.cy,
        Camera::Pinhole(m) => m.cy,
        Camera::PinholeRadTan(m) => m.cy,
        Camera::DoubleSphere(m) => m.cy,
        Camera::Unified(m) => m.cy,
        Camera::ExtendedUnified(m) => m.cy,
        Camera::Scaramuzza(m) => m.cy,
        Camera::Equirectangular(m) => m.cv,
    }
}

fn format_error(path: &Path, message: String) -> Error {
    Error::Format {
        path: path.to_path_buf(),
        message,
    }
}

fn camera_error(path: &Path, field: &str, message: String) -> Error {
    Error::Camera {
        path: path.to_path_buf(),
        field: field.to_string(),
        message,
    }
}

// ---------------------------------------------------------------------------------------------
// Structured text: YAML and JSON as one tree
// ---------------------------------------------------------------------------------------------

/// Parses YAML (a leading OpenCV `%YAML:1.0` line, which is not valid YAML, is skipped; tags
/// such as `!!opencv-matrix` are ignored) or JSON (text starting with `{`) into a JSON tree.
fn parse_tree(text: &str, path: &Path) -> Result<Value> {
    let trimmed = text.trim_start_matches('\u{feff}').trim_start();
    if trimmed.starts_with('{') {
        return serde_json::from_str(trimmed)
            .map_err(|e| format_error(path, format!("not valid JSON: {e}")));
    }
    let body = match trimmed.strip_prefix("%YAML") {
        // Drop the directive line (`%YAML:1.0` or `%YAML 1.x`).
        Some(rest) => rest.split_once('\n').map_or("", |(_, body)| body),
        None => trimmed,
    };
    let docs = yaml_rust2::YamlLoader::load_from_str(body)
        .map_err(|e| format_error(path, format!("not valid YAML: {e}")))?;
    match docs.into_iter().next() {
        Some(doc) => Ok(yaml_to_json(&doc)),
        None => Err(format_error(path, "empty file".to_string())),
    }
}

fn yaml_to_json(y: &yaml_rust2::Yaml) -> Value {
    use yaml_rust2::Yaml;
    match y {
        Yaml::Real(s) => parse_float(s).map_or_else(|| Value::String(s.clone()), Value::from),
        Yaml::Integer(i) => Value::from(*i),
        Yaml::String(s) => Value::String(s.clone()),
        Yaml::Boolean(b) => Value::Bool(*b),
        Yaml::Array(items) => Value::Array(items.iter().map(yaml_to_json).collect()),
        Yaml::Hash(map) => Value::Object(
            map.iter()
                .map(|(k, v)| {
                    let key = match k {
                        Yaml::String(s) | Yaml::Real(s) => s.clone(),
                        Yaml::Integer(i) => i.to_string(),
                        Yaml::Boolean(b) => b.to_string(),
                        _ => String::new(),
                    };
                    (key, yaml_to_json(v))
                })
                .collect(),
        ),
        Yaml::Null | Yaml::Alias(_) | Yaml::BadValue => Value::Null,
    }
}

/// A float as YAML writers print it, including OpenCV's `1.` and `1.e-03`.
fn parse_float(s: &str) -> Option<f64> {
    let s = s.trim();
    s.parse::<f64>()
        .ok()
        .or_else(|| s.replace(".e", ".0e").replace(".E", ".0E").parse().ok())
}

/// A number at `field` of `v` (numbers, or strings holding one).
fn number(v: &Value, path: &Path, field: &str) -> Result<f64> {
    let x = match v {
        Value::Number(n) => n.as_f64(),
        Value::String(s) => parse_float(s),
        _ => None,
    };
    x.ok_or_else(|| camera_error(path, field, format!("expected a number, found {v}")))
}

fn numbers(v: &Value, path: &Path, field: &str) -> Result<Vec<f64>> {
    match v {
        Value::Array(items) => items
            .iter()
            .enumerate()
            .map(|(i, x)| number(x, path, &format!("{field}[{i}]")))
            .collect(),
        other => Err(camera_error(
            path,
            field,
            format!("expected a list of numbers, found {other}"),
        )),
    }
}

fn get<'a>(v: &'a Value, key: &str, path: &Path, field: &str) -> Result<&'a Value> {
    v.get(key)
        .ok_or_else(|| camera_error(path, field, "missing".to_string()))
}

/// A non-negative integer image dimension.
fn dimension(v: &Value, path: &Path, field: &str) -> Result<usize> {
    let x = number(v, path, field)?;
    if x >= 1.0 && x.fract() == 0.0 && x < 1e9 {
        Ok(x as usize)
    } else {
        Err(camera_error(
            path,
            field,
            format!("expected a positive whole number of pixels, found {x}"),
        ))
    }
}

/// `[w, h]` from a two-element list.
fn size_pair(v: &Value, path: &Path, field: &str) -> Result<[usize; 2]> {
    match v {
        Value::Array(items) if items.len() == 2 => Ok([
            dimension(&items[0], path, &format!("{field}[0]"))?,
            dimension(&items[1], path, &format!("{field}[1]"))?,
        ]),
        other => Err(camera_error(
            path,
            field,
            format!("expected [width, height], found {other}"),
        )),
    }
}

fn expect_len(values: &[f64], n: usize, path: &Path, field: &str, what: &str) -> Result<()> {
    if values.len() == n {
        Ok(())
    } else {
        Err(camera_error(
            path,
            field,
            format!("{what}: expected {n} values, found {}", values.len()),
        ))
    }
}

// ---------------------------------------------------------------------------------------------
// Kalibr
// ---------------------------------------------------------------------------------------------

const KALIBR_SUPPORTED: &str =
    "pinhole-equi, pinhole-radtan, pinhole-none, ds-none, eucm-none, omni-none";

fn kalibr(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    let n = options.camera.unwrap_or(0);
    let key = format!("cam{n}");
    let cam = tree.get(&key).ok_or_else(|| {
        let found: Vec<&String> = tree
            .as_object()
            .map(|o| o.keys().filter(|k| k.starts_with("cam")).collect())
            .unwrap_or_default();
        camera_error(
            path,
            &key,
            format!("no such camera in the camchain (found: {found:?}); choose with --camera"),
        )
    })?;
    let field = |name: &str| format!("{key}.{name}");
    let camera_model = get(cam, "camera_model", path, &field("camera_model"))?
        .as_str()
        .unwrap_or_default()
        .to_string();
    let distortion = match cam.get("distortion_model") {
        None | Some(Value::Null) => "none".to_string(),
        Some(v) => v.as_str().unwrap_or_default().to_string(),
    };
    let intrinsics = numbers(
        get(cam, "intrinsics", path, &field("intrinsics"))?,
        path,
        &field("intrinsics"),
    )?;
    let coeffs = match cam.get("distortion_coeffs") {
        None | Some(Value::Null) => Vec::new(),
        Some(v) => numbers(v, path, &field("distortion_coeffs"))?,
    };
    let size = size_pair(
        get(cam, "resolution", path, &field("resolution"))?,
        path,
        &field("resolution"),
    )?;
    let short = match distortion.as_str() {
        "equidistant" => "equi",
        other => other,
    };
    let name = format!("{camera_model}-{short}");
    let ints = |n: usize, what: &str| expect_len(&intrinsics, n, path, &field("intrinsics"), what);
    let coefs =
        |n: usize, what: &str| expect_len(&coeffs, n, path, &field("distortion_coeffs"), what);
    let zero_coeffs = coeffs.iter().all(|c| *c == 0.0);
    let mut notes = Vec::new();
    let model = match (camera_model.as_str(), distortion.as_str()) {
        ("pinhole", "equidistant") => {
            ints(4, "[fu, fv, pu, pv]")?;
            coefs(4, "[k1, k2, k3, k4]")?;
            Model::KannalaBrandt {
                f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                k: [coeffs[0], coeffs[1], coeffs[2], coeffs[3]],
            }
        }
        ("pinhole", "radtan") => {
            ints(4, "[fu, fv, pu, pv]")?;
            coefs(4, "[k1, k2, p1, p2]")?;
            notes.push("k3 = 0: Kalibr's radtan has four coefficients".to_string());
            Model::RadTan {
                f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                k: [coeffs[0], coeffs[1], 0.0],
                p: [coeffs[2], coeffs[3]],
            }
        }
        ("pinhole", "none") => {
            ints(4, "[fu, fv, pu, pv]")?;
            Model::Pinhole {
                f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
            }
        }
        ("ds", "none") => {
            ints(6, "[xi, alpha, fu, fv, pu, pv]")?;
            Model::DoubleSphere {
                f: [intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]],
                xi: intrinsics[0],
                alpha: intrinsics[1],
            }
        }
        ("eucm", "none") => {
            ints(6, "[alpha, beta, fu, fv, pu, pv]")?;
            Model::ExtendedUnified {
                f: [intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]],
                alpha: intrinsics[0],
                beta: intrinsics[1],
            }
        }
        ("omni", "none") | ("omni", "radtan") if zero_coeffs => {
            ints(5, "[xi, fu, fv, pu, pv]")?;
            let xi = intrinsics[0];
            if xi.is_nan() || xi <= -1.0 {
                return Err(camera_error(
                    path,
                    &field("intrinsics"),
                    format!("omni xi = {xi} must be > -1"),
                ));
            }
            notes.push(format!(
                "Kalibr omni (Mei, xi = {xi:?}) as the unified model: alpha = xi / (1 + xi), \
                 fx = fu / (1 + xi), fy = fv / (1 + xi)"
            ));
            Model::Unified {
                f: [
                    intrinsics[1] / (1.0 + xi),
                    intrinsics[2] / (1.0 + xi),
                    intrinsics[3],
                    intrinsics[4],
                ],
                alpha: xi / (1.0 + xi),
            }
        }
        _ => {
            let detail = if camera_model == "omni" && distortion == "radtan" {
                " (with non-zero distortion coefficients)"
            } else {
                ""
            };
            return Err(camera_error(
                path,
                &field("camera_model"),
                format!(
                    "Kalibr model `{name}`{detail} is not supported (supported: {KALIBR_SUPPORTED})"
                ),
            ));
        }
    };
    Ok(Parsed {
        model,
        size,
        source: format!("kalibr {key} ({name})"),
        notes,
    })
}

// ---------------------------------------------------------------------------------------------
// OpenCV
// ---------------------------------------------------------------------------------------------

const OPENCV_K_KEYS: [&str; 4] = ["camera_matrix", "cameraMatrix", "K", "intrinsic_matrix"];
const OPENCV_D_KEYS: [&str; 5] = [
    "distortion_coefficients",
    "dist_coeffs",
    "distCoeffs",
    "D",
    "distortion",
];

/// The first of `keys` present in `tree`, with its name.
fn first_key<'a>(tree: &'a Value, keys: &[&'a str]) -> Option<(&'a str, &'a Value)> {
    keys.iter().find_map(|k| tree.get(*k).map(|v| (*k, v)))
}

/// A matrix as OpenCV's FileStorage writes it (`{rows, cols, dt, data}`, tagged
/// `!!opencv-matrix` in YAML, `"type_id": "opencv-matrix"` in JSON), a nested list, or a flat
/// list: its values in row-major order.
fn matrix(v: &Value, path: &Path, field: &str) -> Result<Vec<f64>> {
    match v {
        Value::Object(m) => {
            let data = numbers(
                m.get("data")
                    .ok_or_else(|| camera_error(path, field, "matrix without `data`".into()))?,
                path,
                &format!("{field}.data"),
            )?;
            if let (Some(r), Some(c)) = (m.get("rows"), m.get("cols")) {
                let (r, c) = (number(r, path, field)?, number(c, path, field)?);
                if (r * c) as usize != data.len() {
                    return Err(camera_error(
                        path,
                        field,
                        format!("{r}x{c} matrix with {} values", data.len()),
                    ));
                }
            }
            Ok(data)
        }
        Value::Array(rows) if rows.iter().all(|r| r.is_array()) => {
            let mut out = Vec::new();
            for (i, row) in rows.iter().enumerate() {
                out.extend(numbers(row, path, &format!("{field}[{i}]"))?);
            }
            Ok(out)
        }
        other => numbers(other, path, field),
    }
}

fn opencv(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    let (k_key, k_value) = first_key(&tree, &OPENCV_K_KEYS).ok_or_else(|| {
        camera_error(
            path,
            "camera_matrix",
            format!("no camera matrix (looked for {OPENCV_K_KEYS:?})"),
        )
    })?;
    let k = matrix(k_value, path, k_key)?;
    expect_len(&k, 9, path, k_key, "a 3x3 camera matrix")?;
    if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
        return Err(camera_error(
            path,
            k_key,
            format!(
                "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (skew is not supported), found \
                 {k:?}"
            ),
        ));
    }
    let f = [k[0], k[4], k[2], k[5]];
    let (d_key, d_value) = first_key(&tree, &OPENCV_D_KEYS).ok_or_else(|| {
        camera_error(
            path,
            "distortion_coefficients",
            format!("no distortion coefficients (looked for {OPENCV_D_KEYS:?})"),
        )
    })?;
    let d = matrix(d_value, path, d_key)?;
    let size = if let (Some(w), Some(h)) = (tree.get("image_width"), tree.get("image_height")) {
        [
            dimension(w, path, "image_width")?,
            dimension(h, path, "image_height")?,
        ]
    } else if let Some((key, v)) = first_key(&tree, &["image_size", "imageSize", "resolution"]) {
        let values = matrix(v, path, key)?;
        expect_len(&values, 2, path, key, "[width, height]")?;
        let pair = Value::from(values);
        size_pair(&pair, path, key)?
    } else {
        return Err(camera_error(
            path,
            "image_width",
            "no image size (looked for image_width + image_height, image_size, imageSize, \
             resolution)"
                .to_string(),
        ));
    };
    // Which model: the command line, then the file, then the number of coefficients.
    let from_file = if let Some(v) = tree.get("fisheye_model") {
        // OpenCV's camera_calibration sample writes `fisheye_model: 0 | 1`.
        match v {
            Value::Bool(b) => Some(*b),
            other => Some(number(other, path, "fisheye_model")? != 0.0),
        }
        .map(|fisheye| {
            if fisheye {
                OpenCvModel::Fisheye
            } else {
                OpenCvModel::Standard
            }
        })
    } else if let Some((key, v)) = first_key(&tree, &["distortion_model", "model"]) {
        match v.as_str().unwrap_or_default() {
            "fisheye" | "equidistant" | "kannala_brandt" | "kannala-brandt" => {
                Some(OpenCvModel::Fisheye)
            }
            "plumb_bob" | "radtan" | "radial-tangential" | "standard" | "pinhole" => {
                Some(OpenCvModel::Standard)
            }
            other => {
                return Err(camera_error(
                    path,
                    key,
                    format!(
                        "OpenCV model `{other}` is not supported (supported: fisheye, \
                         equidistant, plumb_bob, radtan)"
                    ),
                ))
            }
        }
    } else {
        None
    };
    let model = match options.opencv_model.or(from_file) {
        Some(m) => m,
        None if d.len() == 4 => {
            return Err(camera_error(
                path,
                d_key,
                "4 coefficients fit both OpenCV's fisheye model (k1..k4) and the standard one \
                 (k1 k2 p1 p2), and the file does not say which: pass --opencv-model fisheye or \
                 --opencv-model standard"
                    .to_string(),
            ))
        }
        None => OpenCvModel::Standard,
    };
    let mut notes = Vec::new();
    let (model, name) = match model {
        OpenCvModel::Fisheye => {
            expect_len(&d, 4, path, d_key, "fisheye [k1, k2, k3, k4]")?;
            (
                Model::KannalaBrandt {
                    f,
                    k: [d[0], d[1], d[2], d[3]],
                },
                "fisheye",
            )
        }
        OpenCvModel::Standard => {
            let extra = d.get(5..).unwrap_or_default();
            if ![4, 5, 8, 12, 14].contains(&d.len()) {
                return Err(camera_error(
                    path,
                    d_key,
                    format!(
                        "OpenCV's standard model has 4, 5, 8, 12 or 14 coefficients, found {}",
                        d.len()
                    ),
                ));
            }
            if extra.iter().any(|c| *c != 0.0) {
                return Err(camera_error(
                    path,
                    d_key,
                    format!(
                        "OpenCV's rational / thin-prism / tilted model (non-zero k4.. of {} \
                         coefficients) is not supported; only k1 k2 p1 p2 k3",
                        d.len()
                    ),
                ));
            }
            if d.len() == 4 {
                notes.push("k3 = 0: the file has four coefficients".to_string());
            }
            (
                Model::RadTan {
                    f,
                    k: [d[0], d[1], d.get(4).copied().unwrap_or(0.0)],
                    p: [d[2], d[3]],
                },
                "standard",
            )
        }
    };
    Ok(Parsed {
        model,
        size,
        source: format!("opencv ({name} model)"),
        notes,
    })
}

// ---------------------------------------------------------------------------------------------
// Basalt
// ---------------------------------------------------------------------------------------------

fn basalt(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    // cereal wraps the object in `value0`.
    let root = tree.get("value0").unwrap_or(&tree);
    let n = options.camera.unwrap_or(0);
    let list = get(root, "intrinsics", path, "value0.intrinsics")?
        .as_array()
        .ok_or_else(|| camera_error(path, "value0.intrinsics", "expected a list".into()))?;
    let field = format!("value0.intrinsics[{n}]");
    let entry = list.get(n).ok_or_else(|| {
        camera_error(
            path,
            &field,
            format!(
                "the file has {} camera(s); choose with --camera",
                list.len()
            ),
        )
    })?;
    let camera_type = get(entry, "camera_type", path, &format!("{field}.camera_type"))?
        .as_str()
        .unwrap_or_default()
        .to_string();
    let params = get(entry, "intrinsics", path, &format!("{field}.intrinsics"))?;
    let p = |name: &str| {
        let f = format!("{field}.intrinsics.{name}");
        number(get(params, name, path, &f)?, path, &f)
    };
    let resolution = get(root, "resolution", path, "value0.resolution")?;
    let size = match resolution.as_array().and_then(|r| r.get(n)) {
        Some(pair) => size_pair(pair, path, &format!("value0.resolution[{n}]"))?,
        None => {
            return Err(camera_error(
                path,
                "value0.resolution",
                format!("no resolution for camera {n}"),
            ))
        }
    };
    let f = || -> Result<[f64; 4]> { Ok([p("fx")?, p("fy")?, p("cx")?, p("cy")?]) };
    let model = match camera_type.as_str() {
        "kb4" => Model::KannalaBrandt {
            f: f()?,
            k: [p("k1")?, p("k2")?, p("k3")?, p("k4")?],
        },
        "ds" => Model::DoubleSphere {
            f: f()?,
            xi: p("xi")?,
            alpha: p("alpha")?,
        },
        "eucm" => Model::ExtendedUnified {
            f: f()?,
            alpha: p("alpha")?,
            beta: p("beta")?,
        },
        "ucm" => Model::Unified {
            f: f()?,
            alpha: p("alpha")?,
        },
        "pinhole" => Model::Pinhole { f: f()? },
        other => {
            return Err(camera_error(
                path,
                &format!("{field}.camera_type"),
                format!(
                    "Basalt camera type `{other}` is not supported (supported: kb4, ds, eucm, \
                     ucm, pinhole)"
                ),
            ))
        }
    };
    Ok(Parsed {
        model,
        size,
        source: format!("basalt intrinsics[{n}] ({camera_type})"),
        notes: Vec::new(),
    })
}

// ---------------------------------------------------------------------------------------------
// COLMAP
// ---------------------------------------------------------------------------------------------

/// COLMAP's image coordinates put the centre of the top-left pixel at (0.5, 0.5).
const COLMAP_PIXEL_CENTRE: f64 = 0.5;

fn colmap(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let lines: Vec<(usize, Vec<&str>)> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.split_whitespace().collect()))
        .collect();
    let id_of = |tokens: &[&str]| tokens.first().and_then(|t| t.parse::<usize>().ok());
    let (line, tokens) = match options.camera {
        None => lines.first(),
        Some(id) => lines.iter().find(|(_, t)| id_of(t) == Some(id)),
    }
    .ok_or_else(|| {
        let ids: Vec<usize> = lines.iter().filter_map(|(_, t)| id_of(t)).collect();
        format_error(
            path,
            match options.camera {
                Some(id) => format!("no camera with CAMERA_ID {id} (found {ids:?})"),
                None => "no camera line (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...)".to_string(),
            },
        )
    })?;
    let field = |what: &str| format!("line {line}: {what}");
    if tokens.len() < 4 {
        return Err(camera_error(
            path,
            &field("CAMERA_ID MODEL WIDTH HEIGHT"),
            format!("expected at least 4 tokens, found {}", tokens.len()),
        ));
    }
    let id = tokens[0];
    let name = tokens[1];
    let dim = |t: &str, what: &str| {
        t.parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| camera_error(path, &field(what), format!("`{t}` is not a size")))
    };
    let size = [dim(tokens[2], "WIDTH")?, dim(tokens[3], "HEIGHT")?];
    let params = tokens[4..]
        .iter()
        .map(|t| {
            parse_float(t).ok_or_else(|| {
                camera_error(path, &field("PARAMS"), format!("`{t}` is not a number"))
            })
        })
        .collect::<Result<Vec<f64>>>()?;
    let count = |n: usize, names: &str| {
        expect_len(
            &params,
            n,
            path,
            &field("PARAMS"),
            &format!("{name} {names}"),
        )
    };
    let c = COLMAP_PIXEL_CENTRE;
    let model = match name {
        "SIMPLE_PINHOLE" => {
            count(3, "f, cx, cy")?;
            Model::Pinhole {
                f: [params[0], params[0], params[1] - c, params[2] - c],
            }
        }
        "PINHOLE" => {
            count(4, "fx, fy, cx, cy")?;
            Model::Pinhole {
                f: [params[0], params[1], params[2] - c, params[3] - c],
            }
        }
        "SIMPLE_RADIAL" => {
            count(4, "f, cx, cy, k")?;
            Model::RadTan {
                f: [params[0], params[0], params[1] - c, params[2] - c],
                k: [params[3], 0.0, 0.0],
                p: [0.0, 0.0],
            }
        }
        "RADIAL" => {
            count(5, "f, cx, cy, k1, k2")?;
            Model::RadTan {
                f: [params[0], params[0], params[1] - c, params[2] - c],
                k: [params[3], params[4], 0.0],
                p: [0.0, 0.0],
            }
        }
        "OPENCV" => {
            count(8, "fx, fy, cx, cy, k1, k2, p1, p2")?;
            Model::RadTan {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                k: [params[4], params[5], 0.0],
                p: [params[6], params[7]],
            }
        }
        "FULL_OPENCV" => {
            count(12, "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6")?;
            if params[9..].iter().any(|v| *v != 0.0) {
                return Err(camera_error(
                    path,
                    &field("PARAMS"),
                    "FULL_OPENCV with non-zero k4, k5, k6 (OpenCV's rational model) is not \
                     supported"
                        .to_string(),
                ));
            }
            Model::RadTan {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                k: [params[4], params[5], params[8]],
                p: [params[6], params[7]],
            }
        }
        "OPENCV_FISHEYE" => {
            count(8, "fx, fy, cx, cy, k1, k2, k3, k4")?;
            Model::KannalaBrandt {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                k: [params[4], params[5], params[6], params[7]],
            }
        }
        other => {
            return Err(camera_error(
                path,
                &field("MODEL"),
                format!(
                    "COLMAP model `{other}` is not supported (supported: OPENCV_FISHEYE, \
                     OPENCV, FULL_OPENCV with zero k4..k6, PINHOLE, SIMPLE_PINHOLE, \
                     SIMPLE_RADIAL, RADIAL)"
                ),
            ))
        }
    };
    Ok(Parsed {
        model,
        size,
        source: format!("colmap camera {id} ({name})"),
        notes: vec![
            "cx, cy: COLMAP's minus 0.5 px (COLMAP puts the top-left pixel centre at (0.5, 0.5), \
             this file at (0, 0))"
                .to_string(),
        ],
    })
}

// ---------------------------------------------------------------------------------------------
// OCamCalib
// ---------------------------------------------------------------------------------------------

fn ocamcalib(text: &str, path: &Path) -> Result<Parsed> {
    // The data lines, in order, between '#' comment lines (ocam_functions.c, get_ocam_model).
    let lines: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l))
        .collect();
    const BLOCKS: [&str; 5] = [
        "direct polynomial (length, a0 .. aN)",
        "inverse polynomial (length, b0 .. bM)",
        "centre (row, column)",
        "affine parameters (c, d, e)",
        "image size (height, width)",
    ];
    if lines.len() < BLOCKS.len() {
        return Err(format_error(
            path,
            format!(
                "expected {} data lines ({}), found {}",
                BLOCKS.len(),
                BLOCKS.join("; "),
                lines.len()
            ),
        ));
    }
    let values = |k: usize| -> Result<Vec<f64>> {
        let (line, text) = lines[k];
        text.split_whitespace()
            .map(|t| {
                parse_float(t).ok_or_else(|| {
                    camera_error(
                        path,
                        &format!("line {line}: {}", BLOCKS[k]),
                        format!("`{t}` is not a number"),
                    )
                })
            })
            .collect()
    };
    let block_field = |k: usize| format!("line {}: {}", lines[k].0, BLOCKS[k]);
    let polynomial = |k: usize| -> Result<Vec<f64>> {
        let v = values(k)?;
        let n = v.first().copied().unwrap_or(-1.0);
        if !(n >= 1.0 && n.fract() == 0.0 && v.len() == n as usize + 1) {
            return Err(camera_error(
                path,
                &block_field(k),
                format!(
                    "the first number is the count of coefficients that follow: {n} vs {}",
                    v.len().saturating_sub(1)
                ),
            ));
        }
        Ok(v[1..].to_vec())
    };
    let poly = polynomial(0)?;
    let inv_poly = polynomial(1)?;
    let fixed = |k: usize, n: usize| -> Result<Vec<f64>> {
        let v = values(k)?;
        expect_len(&v, n, path, &block_field(k), BLOCKS[k])?;
        Ok(v)
    };
    let centre = fixed(2, 2)?;
    let cde = fixed(3, 3)?;
    let hw = fixed(4, 2)?;
    let dim = |x: f64, what: &str| {
        if x >= 1.0 && x.fract() == 0.0 {
            Ok(x as usize)
        } else {
            Err(camera_error(
                path,
                &block_field(4),
                format!("{what} = {x} is not a size"),
            ))
        }
    };
    let size = [dim(hw[1], "width")?, dim(hw[0], "height")?];
    Ok(Parsed {
        model: Model::Scaramuzza {
            poly,
            inv_poly,
            // OCamCalib: xc = row, yc = column.
            centre: [centre[1], centre[0]],
            cde: [cde[0], cde[1], cde[2]],
        },
        size,
        source: "ocamcalib calib_results".to_string(),
        notes: vec![
            "cx = OCamCalib's yc (column), cy = its xc (row); c, d, e in OCamCalib's order"
                .to_string(),
        ],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opencv_floats_parse() {
        assert_eq!(parse_float("1."), Some(1.0));
        assert_eq!(parse_float("2.8700000000000000e+02"), Some(287.0));
        assert_eq!(parse_float("1.e-03"), Some(1e-3));
        assert_eq!(parse_float("-.5"), Some(-0.5));
        assert_eq!(parse_float("x"), None);
    }

    #[test]
    fn formats_and_models_parse_from_their_names() {
        for f in ["kalibr", "opencv", "basalt", "colmap", "ocamcalib"] {
            assert_eq!(f.parse::<Format>().unwrap().to_string(), f);
        }
        assert!("matlab".parse::<Format>().unwrap_err().contains("kalibr"));
        assert_eq!("fisheye".parse::<OpenCvModel>(), Ok(OpenCvModel::Fisheye));
        assert!("omni".parse::<OpenCvModel>().is_err());
    }
}
