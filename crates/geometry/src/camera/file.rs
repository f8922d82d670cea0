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
//! | `pinhole-radtan` | `fx fy cx cy k1 k2 p1 p2 k3`, optional `k4 k5 k6` (OpenCV's rational model) and `rpmax` (a bound on the undistorted radius, Basalt's) (OpenCV order and meaning; fov derived) |
//! | `double-sphere` | `fov_deg fx fy cx cy xi alpha` |
//! | `unified` | `fov_deg fx fy cx cy alpha` |
//! | `extended-unified` | `fov_deg fx fy cx cy alpha beta` |
//! | `mei` | `fov_deg fx fy cx cy xi k1 k2 p1 p2` (Kalibr `omni-radtan`: `fx` is Mei's gamma) |
//! | `fov` | `fov_deg fx fy cx cy w` (Devernay and Faugeras) |
//! | `scaramuzza` | `fov_deg cx cy c d e poly`, optional `inv_poly` (OCamCalib; `cx` is the column) |
//! | `equirectangular` | none |
//!
//! Reading goes text -> `toml::Table` (for `model`) -> the model's `Raw` (serde,
//! `deny_unknown_fields`, so a misspelt key is an error naming it; each model file declares its
//! own) -> the model's validating constructor. Checks: every float finite, `fx, fy > 0`,
//! `width, height > 0`, `0 < fov_deg < 360`; Kannala-Brandt: a polynomial that increases on
//! `[0, fov_deg / 2]`; radial-tangential: `rpmax >= 0` (a distortion that folds inside the image
//! is valid: pixels past the fold are outside the model); Mei: `xi >= 0`; FOV: `0 < w < pi`;
//! double sphere: `xi in (-1, 1]`, `alpha in [0, 1]`;
//! unified: `alpha in [0, 1)`; extended unified: `alpha in [0, 1]`, `beta > 0`; Scaramuzza:
//! `a0 < 0`, `c - d e > 0`; every fisheye model: `fov_deg / 2` below the model's largest
//! projectable angle. Errors name the file and the field.
//!
//! [`to_toml`] writes the same format (used by `calibconv camera import`).

use std::path::Path;

use super::schema::CameraFile;
use super::{Camera, MODELS};
use crate::error::{Error, Result};

/// The model's `Raw` (deserialised from the text, not a table, so that errors point at the
/// line), then its validating constructor.
pub(super) fn read<M: CameraFile>(text: &str, path: &Path) -> Result<M> {
    let raw: M::Raw = toml::from_str(text).map_err(|e| toml_error(path, e))?;
    M::from_raw(raw).map_err(|e| e.in_file(path))
}

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
                format!("missing; expected one of {}", known()),
            ))
        }
        Some(toml::Value::String(model)) => model.as_str(),
        Some(other) => {
            return Err(camera_error(
                path,
                format!("expected a string, one of {}, found {other}", known()),
            ))
        }
    };
    match Camera::read_model(model, text, path) {
        Some(camera) => camera,
        None => Err(camera_error(
            path,
            format!("unknown model `{model}`; expected one of {}", known()),
        )),
    }
}

/// The text of a camera file for `camera`: `header` lines as `#` comments, then `name` and
/// `description` when given, then `model` and every field of the model by name (each model's
/// `CameraFile::write_fields`). Floats are written as the shortest text that reads back to the
/// same `f64`, so [`parse`] returns `camera` again.
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
    camera.write_fields(&mut out);
    out
}

/// An error in the `model` key.
fn camera_error(path: &Path, message: String) -> Error {
    Error::Camera {
        path: path.to_path_buf(),
        field: "model".to_string(),
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

#[cfg(test)]
mod tests {
    use std::f64::consts::FRAC_PI_2;
    use std::path::PathBuf;

    use super::*;
    use crate::camera::tests::{self, angle, cameras_dir, kb};
    use crate::camera::{
        load, CameraModel, DoubleSphere, Equirectangular, Intrinsics, Pinhole, PixelConvention,
    };

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
        cameras_dir().join(name)
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

    /// `text` is refused naming `field`, with every one of `words` in the message.
    fn assert_refused(text: &str, field: &str, words: &[&str]) {
        let e = bad(text);
        assert_eq!(field_of(&e), field, "{e}");
        let msg = e.to_string();
        assert!(words.iter().all(|w| msg.contains(w)), "{msg}");
    }

    #[test]
    fn shipped_files_hold_the_documented_values() {
        let f195 = load(shipped("f195.toml")).unwrap();
        assert_eq!(f195, Camera::KannalaBrandt(tests::f195()));
        let f165 = load(shipped("f165.toml")).unwrap();
        assert_eq!(
            f165,
            Camera::KannalaBrandt(kb(326.0, 326.0, 540.0, 480.0, [0.0; 4], 1080, 960, 165.0))
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
            Camera::Pinhole(
                Pinhole::new(Intrinsics::from_parts(
                    [540.0, 540.0, 540.0, 480.0],
                    [1080, 960]
                ))
                .unwrap()
            )
        );
        assert!((pers.fov() - FRAC_PI_2).abs() < 1e-15);
        // EuRoC MAV cam0 (sensor.yaml, Kalibr pinhole-radtan, k3 = 0).
        assert_eq!(
            load(shipped("radtan_example.toml")).unwrap(),
            Camera::PinholeRadTan(tests::euroc())
        );
        assert_eq!(
            load(shipped("equirect.toml")).unwrap(),
            Camera::Equirectangular(Equirectangular::new(1024, 512).unwrap())
        );
        assert_eq!(
            load(shipped("ds_example.toml")).unwrap(),
            Camera::DoubleSphere(
                DoubleSphere::new(
                    Intrinsics::from_parts([158.28, 158.27, 254.96, 256.88], [512, 512]),
                    -0.172,
                    0.593,
                    153.4
                )
                .unwrap()
            )
        );
    }

    /// Every camera file in `data/cameras/`, sorted by name.
    fn shipped_cameras() -> Vec<(String, Camera)> {
        let mut names: Vec<String> = std::fs::read_dir(cameras_dir())
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
            Camera::Mei(m) => [m.cx, m.cy],
            Camera::Fov(m) => [m.cx, m.cy],
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
            Camera::Mei(m) => m.fx / (1.0 + m.xi),
            Camera::Fov(m) => m.fx * 2.0 * (m.w / 2.0).tan() / m.w,
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
            Camera::Mei(m) => Some(m.theta_max()),
            Camera::Fov(_) => Some(std::f64::consts::PI),
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
            assert_refused(&text, "model", &["kannala-brandt", "pinhole"]);
        }
    }

    #[test]
    fn polynomial_folding_inside_the_declared_fov_is_rejected() {
        // d' = 1 - 1.5 theta^2 + ... vanishes near 46.8 deg, long before 97.5 deg.
        let text = f195_text().replace("k1 = 3.37012024344156e-19", "k1 = -0.5");
        assert_refused(&text, "k1..k4", &["stops increasing", "97.500"]);
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
        let cam = Camera::KannalaBrandt(kb(
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
        // (file, text replaced, replacement, the field the error names)
        let cases = [
            ("ds_example.toml", "xi = -0.172", "xi = -1.0", "xi"),
            ("ds_example.toml", "xi = -0.172", "xi = 1.5", "xi"),
            ("ds_example.toml", "alpha = 0.593", "alpha = 1.2", "alpha"),
            ("ds_example.toml", "fx = 158.28", "fx = nan", "fx"),
            ("ucm_example.toml", "alpha = 0.48", "alpha = 1.0", "alpha"),
            ("ucm_example.toml", "alpha = 0.48", "alpha = -0.1", "alpha"),
            ("eucm_example.toml", "beta = 1.2", "beta = 0.0", "beta"),
            ("eucm_example.toml", "alpha = 0.45", "alpha = 2.0", "alpha"),
            ("ocam_example.toml", "[-181.0,", "[181.0,", "poly"),
            ("ocam_example.toml", "c = 1.0003", "c = -1.0", "c, d, e"),
            ("ocam_example.toml", "[-181.0,", "[-181.0, inf,", "poly"),
            ("equirect.toml", "width = 1024", "width = 0", "width"),
        ];
        for (name, from, to, field) in cases {
            let text = shipped_text(name);
            assert!(text.contains(from), "{name} has no `{from}`");
            assert_eq!(
                field_of(&bad(&text.replace(from, to))),
                field,
                "{name}: {to}"
            );
        }
        // theta_max is ~125.3 deg for these xi, alpha: a 260 degree lens does not fit.
        let ds = shipped_text("ds_example.toml");
        let wide = ds.replace("fov_deg = 153.4", "fov_deg = 260.0");
        assert_refused(&wide, "fov_deg", &["xi, alpha"]);

        let ocam = shipped_text("ocam_example.toml");
        // rho f' - f = 181 + 0.01 rho^2 - 2e-4 rho^3 vanishes near rho = 117 px (theta ~ 30 deg).
        let folding = ocam
            .lines()
            .map(|l| match l.starts_with("poly") {
                true => "poly = [-181.0, 0.0, 0.01, -1e-4]\n".to_string(),
                false => format!("{l}\n"),
            })
            .collect::<String>();
        assert_refused(&folding, "fov_deg", &["poly"]);
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
        let msg = bad(&format!("{eq}fov_deg = 360.0\n")).to_string();
        assert!(msg.contains("fov_deg"), "{msg}");
    }

    #[test]
    fn radtan_folding_inside_the_image_reads_with_its_domain() {
        // k1 = -0.5 folds at r = sqrt(2/3) = 0.816 on the z = 1 plane; the EuRoC image corner
        // is at r ~ 0.98, so the distortion folds inside the image: the corner is outside the
        // model, the centre is not.
        let text = shipped_text("radtan_example.toml")
            .replace("k1 = -0.28340811", "k1 = -0.5")
            .replace("k2 = 0.07395907", "k2 = 0.0");
        let cam = parse(&text, Path::new("fold.toml")).unwrap();
        assert_eq!(cam.unproject([0.0, 0.0]), None);
        assert!(cam.unproject([376.0, 240.0]).is_some());
        // The rational model's fields are optional and read back; a negative bound is refused.
        let rational = format!("{text}k4 = 0.1\nk5 = 0.0\nk6 = 0.01\nrpmax = 1.5\n");
        let cam = parse(&rational, Path::new("rational.toml")).unwrap();
        assert_eq!(
            parse(&to_toml(&cam, &[], None, None), Path::new("back")).unwrap(),
            cam
        );
        let negative = rational.replace("rpmax = 1.5", "rpmax = -1.0");
        assert_refused(&negative, "rpmax", &[">= 0"]);
    }
}
