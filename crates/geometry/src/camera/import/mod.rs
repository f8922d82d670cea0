//! Calibrations of other tools as cameras of this crate (`calibconv camera import`).
//!
//! | `--from` | file | models read |
//! |---|---|---|
//! | `kalibr` | camchain YAML (`camN:` blocks) | `pinhole-equi`, `pinhole-radtan`, `pinhole-fov`, `pinhole-none`, `omni-radtan`, `omni-none`, `ds-none`, `eucm-none` |
//! | `opencv` | `cv::FileStorage` YAML (`%YAML:1.0`, `!!opencv-matrix`), XML (`<opencv_storage>`) or JSON, or plain YAML / JSON; keys in any case (`Camera_Matrix`, `image_Width`) | fisheye (`K`, `D` = k1..k4) and standard (`D` = k1 k2 p1 p2 [k3 [k4 k5 k6]]; thin-prism and tilt terms only when zero) |
//! | `basalt` | calibration JSON (`value0.intrinsics[N]`) | `kb4`, `ds`, `eucm`, `ucm`, `pinhole`, `pinhole-radtan8`, `fov` |
//! | `colmap` | `cameras.txt` | `OPENCV_FISHEYE`, `OPENCV`, `FULL_OPENCV`, `FOV`, `PINHOLE`, `SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL` |
//! | `ocamcalib` | `calib_results.txt` | Scaramuzza's model |
//! | `ros` | `camera_calibration`'s `ost.yaml` or `ost.txt` | `plumb_bob`, `rational_polynomial`, `equidistant` |
//! | `orbslam3` | ORB-SLAM3 settings YAML (`Camera.fx` or `Camera1.fx` keys) | `PinHole`, `KannalaBrandt8`, `Rectified` |
//!
//! Anything else (COLMAP's `THIN_PRISM_FISHEYE`, OpenCV's thin-prism terms, a skewed camera
//! matrix, ...) is an error naming the file and the field.
//!
//! Conventions converted on the way in (all else is copied as is):
//! - COLMAP puts the centre of the top-left pixel at `(0.5, 0.5)`; this crate (like OpenCV,
//!   Kalibr, Basalt, ROS, ORB-SLAM3 and OCamCalib's C export) at `(0, 0)`: COLMAP's `cx`, `cy`
//!   move by -0.5 px.
//! - Kalibr's `omni` is Mei's unified model `u = fu x / (z + xi d) + pu`. Without distortion it
//!   is the crate's `unified` model with `alpha = xi / (1 + xi)` and `fx = fu / (1 + xi)` (same
//!   for `fy`); with radtan coefficients, the `mei` model with Kalibr's values as they are.
//! - OCamCalib's centre is "row, column": `xc` becomes `cy`, `yc` becomes `cx`.
//! - Kalibr `pinhole-radtan` and OpenCV 4-coefficient standard distortion have `k3 = 0`.
//!
//! A skewed camera matrix (`K[0][1] != 0`) is refused, naming the entry: no model here has a
//! skew term, and dropping it would move pixels.
//!
//! The field of view of the fisheye models (`fov_deg`) is rarely in the source file. Unless
//! given (`--fov-deg`), it is the angle the image **width** spans on the principal row: the
//! angle to the optical axis of the left pixel edge `(-0.5, cy)` plus that of the right one
//! `(width - 0.5, cy)`. For a lens whose image circle is narrower than the sensor that is more
//! than the lens sees (pass the lens's `--fov-deg` then); it is an error when an edge lies outside
//! the model's domain. Pinhole models derive their field of view and take no `--fov-deg`.
//!
//! A distortion that folds inside the image (its radius peaks before the image corners, as
//! happens with COLMAP `FULL_OPENCV` and other rational fits) imports with its valid domain:
//! pixels past the fold are outside the model, and [`Imported::outside`] (also a note in the
//! written file) says what fraction of the image that is.
//!
//! JSON numbers are read exactly (serde_json's `float_roundtrip`), YAML, XML and text numbers by
//! Rust's own float parser, so coefficients reach the camera file bit for bit.
//!
//! Every imported camera is built by its model's validating constructor, which the camera-file
//! reader calls too, so it is exactly what the written file will read back as.

use std::path::Path;

mod basalt;
mod colmap;
mod kalibr;
mod ocamcalib;
mod opencv;
mod orbslam3;
mod ros;
mod tree;

use super::schema::checked;
use super::{
    Camera, CameraModel, DoubleSphere, ExtendedUnified, Fov, Intrinsics, Invalid, KannalaBrandt,
    Mei, Pinhole, PinholeRadTan, Scaramuzza, Unified,
};
use crate::error::{Error, Result};
use crate::from_str_by_name;
use crate::vec3::angle_to_axis;

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
    /// ROS `camera_calibration`: `ost.yaml` or `ost.txt`.
    Ros,
    /// ORB-SLAM3 settings YAML.
    OrbSlam3,
}

from_str_by_name!(Format, "format", {
    "kalibr" => Kalibr,
    "opencv" => OpenCv,
    "basalt" => Basalt,
    "colmap" => Colmap,
    "ocamcalib" => OcamCalib,
    "ros" => Ros,
    "orbslam3" => OrbSlam3,
});

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (name, _) = Format::NAMES
            .iter()
            .find(|(_, v)| v == self)
            .expect("every format");
        f.write_str(name)
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

from_str_by_name!(OpenCvModel, "OpenCV model", {
    "fisheye" => Fisheye,
    "standard" => Standard,
});

/// Choices the source file may leave open.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImportOptions {
    /// Which camera of a multi-camera file: Kalibr `camN`, Basalt `intrinsics[N]`, the N-th
    /// camera of a ROS `ost.txt`, ORB-SLAM3 0 (`Camera1`) or 1 (`Camera2`) (default 0); COLMAP
    /// `CAMERA_ID` (default: the first line).
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
    /// The fraction of the image outside the model (pixels that do not unproject: past a
    /// distortion's fold, or outside a fisheye model's domain), measured on a grid of at most
    /// [`OUTSIDE_GRID`] x [`OUTSIDE_GRID`] pixel centres; 0 when the whole image border
    /// unprojects (the domain, a disc-like region around the principal point, then holds the
    /// whole image).
    pub outside: f64,
}

/// Grid points per side on which [`Imported::outside`] is measured (1/128 of the width apart).
pub const OUTSIDE_GRID: usize = 128;

/// Points per image edge checked before measuring [`Imported::outside`] on the grid.
const BORDER_SAMPLES: usize = 256;

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
        Format::Kalibr => kalibr::read(text, path, options)?,
        Format::OpenCv => opencv::read(text, path, options)?,
        Format::Basalt => basalt::read(text, path, options)?,
        Format::Colmap => colmap::read(text, path, options)?,
        Format::OcamCalib => ocamcalib::read(text, path)?,
        Format::Ros => ros::read(text, path, options)?,
        Format::OrbSlam3 => orbslam3::read(text, path, options)?,
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
    /// `k = [k1, .., k6]` (OpenCV's rational model; `k4..k6 = 0` for 5 coefficients),
    /// `rpmax` a bound on the undistorted radius (0: none).
    RadTan {
        f: [f64; 4],
        k: [f64; 6],
        p: [f64; 2],
        rpmax: f64,
    },
    /// Mei's unified model with radtan: `f` = Kalibr's `[fu, fv, pu, pv]`.
    Mei {
        f: [f64; 4],
        xi: f64,
        k: [f64; 2],
        p: [f64; 2],
    },
    /// Devernay-Faugeras FOV.
    Fov {
        f: [f64; 4],
        w: f64,
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

impl Model {
    /// OpenCV's 5-coefficient radial-tangential model, `k = [k1, k2, k3]`.
    fn radtan(f: [f64; 4], k: [f64; 3], p: [f64; 2]) -> Model {
        Model::RadTan {
            f,
            k: [k[0], k[1], k[2], 0.0, 0.0, 0.0],
            p,
            rpmax: 0.0,
        }
    }
}

/// What a reader found: the model (`f` = `[fx, fy, cx, cy]`), the image size, a description.
struct Parsed {
    model: Model,
    size: [usize; 2],
    source: String,
    notes: Vec<String>,
}

/// The camera for `fov_deg` (ignored by the pinhole models), checked as its model's validating
/// constructor checks it: exactly what the written camera file will read back as.
fn build(model: &Model, size: [usize; 2], fov_deg: f64) -> std::result::Result<Camera, Invalid> {
    checked(unchecked(model, size, fov_deg), Camera::validate)
}

/// A fisheye camera without the checks, to probe the model's domain before `fov_deg` is chosen
/// (the domain does not depend on it); `None` for the pinhole models, which derive theirs.
fn probe(model: &Model, size: [usize; 2]) -> Option<Camera> {
    let pinhole = matches!(model, Model::Pinhole { .. } | Model::RadTan { .. });
    (!pinhole).then(|| unchecked(model, size, 180.0))
}

/// The camera of `model` for `fov_deg` (ignored by the pinhole models), through the models'
/// constructors without the checks.
fn unchecked(model: &Model, size: [usize; 2], fov_deg: f64) -> Camera {
    let intrinsics = |f: [f64; 4]| Intrinsics::from_parts(f, size);
    match model.clone() {
        Model::KannalaBrandt { f, k } => {
            Camera::KannalaBrandt(KannalaBrandt::unchecked(intrinsics(f), k, fov_deg))
        }
        Model::Pinhole { f } => Camera::Pinhole(Pinhole::unchecked(intrinsics(f))),
        Model::RadTan { f, k, p, rpmax } => {
            Camera::PinholeRadTan(PinholeRadTan::unchecked(intrinsics(f), k, p, rpmax))
        }
        Model::Mei { f, xi, k, p } => Camera::Mei(Mei::unchecked(intrinsics(f), xi, k, p, fov_deg)),
        Model::Fov { f, w } => Camera::Fov(Fov::unchecked(intrinsics(f), w, fov_deg)),
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
    }
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
    let probe = probe(&model, size);
    let fov = if probe.is_none() {
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
    let fov_deg = match (fov, options.fov_deg, &probe) {
        (FovSource::Given, Some(f), _) => {
            notes.push(format!(
                "fov_deg: {f} deg, given on the command line (--fov-deg)"
            ));
            f
        }
        (FovSource::ImageWidth, _, Some(probe)) => {
            let fov = width_fov(probe, path)?;
            notes.push(format!(
                "fov_deg: {fov} deg, the angle the image width spans on the principal row (the \
                 source does not give it; import with --fov-deg to set the lens's own)"
            ));
            fov
        }
        _ => 180.0, // unused by pinhole models
    };
    let camera = build(&model, size, fov_deg).map_err(|e| e.in_file(path))?;
    let outside = outside_fraction(&camera);
    if outside > 0.0 {
        notes.push(format!(
            "{:.2} % of the image lies outside the model (its pixels do not unproject: past the \
             distortion's fold or the model's domain)",
            100.0 * outside
        ));
    }
    Ok(Imported {
        camera,
        source,
        fov,
        notes,
        outside,
    })
}

/// [`Imported::outside`]: 0 if every point of the image border unprojects, else the fraction of
/// an at most [`OUTSIDE_GRID`]-square grid of pixel centres that does not.
fn outside_fraction(camera: &Camera) -> f64 {
    let [w, h] = camera.size().map(|n| n as f64);
    let border = (0..=BORDER_SAMPLES).flat_map(|i| {
        let t = i as f64 / BORDER_SAMPLES as f64;
        let (u, v) = (-0.5 + t * w, -0.5 + t * h);
        [[u, -0.5], [u, h - 0.5], [-0.5, v], [w - 0.5, v]]
    });
    if border.into_iter().all(|px| camera.unproject(px).is_some()) {
        return 0.0;
    }
    let axis = |n: f64| {
        let steps = OUTSIDE_GRID.min(n as usize);
        (0..steps).map(move |i| (i as f64 + 0.5) * n / steps as f64 - 0.5)
    };
    let (mut outside, mut total) = (0usize, 0usize);
    for v in axis(h) {
        for u in axis(w) {
            total += 1;
            outside += usize::from(camera.unproject([u, v]).is_none());
        }
    }
    outside as f64 / total as f64
}

/// The angle the image width spans on the principal row of `probe` (module docs), rounded down
/// to 1e-3 deg; an error naming `fov_deg` if an image edge lies outside the model's domain.
fn width_fov(probe: &Camera, path: &Path) -> Result<f64> {
    let [w, _] = probe.size();
    let cy = principal_row(probe);
    let mut total = 0.0;
    for u in [-0.5, w as f64 - 0.5] {
        let ray = probe.unproject([u, cy]).ok_or_else(|| {
            camera_error(
                path,
                "fov_deg",
                format!(
                    "the image edge ({u}, {cy}) lies outside the {} model's domain, so the field \
                     of view cannot be taken from the image width: pass --fov-deg",
                    probe.model_name()
                ),
            )
        })?;
        total += angle_to_axis(ray).to_degrees();
    }
    Ok((total * FOV_DECIMALS).floor() / FOV_DECIMALS)
}

/// The principal row of a camera built by [`build`] or [`probe`].
fn principal_row(camera: &Camera) -> f64 {
    match camera {
        Camera::KannalaBrandt(m) => m.cy,
        Camera::Pinhole(m) => m.cy,
        Camera::PinholeRadTan(m) => m.cy,
        Camera::DoubleSphere(m) => m.cy,
        Camera::Unified(m) => m.cy,
        Camera::ExtendedUnified(m) => m.cy,
        Camera::Mei(m) => m.cy,
        Camera::Fov(m) => m.cy,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_and_models_parse_from_their_names() {
        for f in [
            "kalibr",
            "opencv",
            "basalt",
            "colmap",
            "ocamcalib",
            "ros",
            "orbslam3",
        ] {
            assert_eq!(f.parse::<Format>().unwrap().to_string(), f);
        }
        assert!("matlab".parse::<Format>().unwrap_err().contains("kalibr"));
        assert_eq!("fisheye".parse::<OpenCvModel>(), Ok(OpenCvModel::Fisheye));
        assert!("omni".parse::<OpenCvModel>().is_err());
    }
}
