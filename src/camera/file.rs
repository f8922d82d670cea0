//! Camera files: flat TOML with named fields (`data/cameras/*.toml`), never positional arrays.
//!
//! ```toml
//! model = "kannala-brandt"        # or "pinhole"
//! name = "F195"                   # optional, ignored
//! description = "..."             # optional, ignored
//! width = 1080                    # pixels
//! height = 960
//! fov_deg = 195.0                 # kannala-brandt only: full field of view, degrees
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
//! Reading goes text -> `toml::Table` (for `model`) -> `Raw*` (serde, `deny_unknown_fields`, so a
//! misspelt key is an error naming it) -> checked model. Checks: every float finite, `fx, fy > 0`,
//! `width, height > 0`, `0 < fov_deg < 360`, and for Kannala-Brandt a polynomial that increases on
//! `[0, fov_deg / 2]`.

use std::path::Path;

use serde::Deserialize;

use super::{Camera, KannalaBrandt, Pinhole};
use crate::error::{Error, Result};

/// The values of `model` this module reads.
pub const MODELS: [&str; 2] = ["kannala-brandt", "pinhole"];

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
    match model {
        "kannala-brandt" => {
            // Deserialise from the text, not the table, so the error points at the line.
            let raw: RawKannalaBrandt = toml::from_str(text).map_err(|e| toml_error(path, e))?;
            raw.resolve(path).map(Camera::KannalaBrandt)
        }
        "pinhole" => {
            let raw: RawPinhole = toml::from_str(text).map_err(|e| toml_error(path, e))?;
            raw.resolve(path).map(Camera::Pinhole)
        }
        other => Err(camera_error(
            path,
            "model",
            format!("unknown model `{other}`; expected one of {}", known()),
        )),
    }
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
        if !(self.fov_deg > 0.0 && self.fov_deg < 360.0) {
            return Err(camera_error(
                path,
                "fov_deg",
                format!("must be in (0, 360) degrees, found {}", self.fov_deg),
            ));
        }
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

#[cfg(test)]
mod tests {
    use std::f64::consts::FRAC_PI_2;
    use std::path::PathBuf;

    use super::*;
    use crate::camera::{load, CameraModel, PixelConvention};

    /// Pixel round trips: Newton stops at |step| < 1e-12 rad with quadratic convergence, so the
    /// error is round-off, ~fx * 1e-15 ~ 1e-12 px; 1e-9 px is margin, not slack for a bug.
    const PX_TOL: f64 = 1e-9;
    /// Ray round trips in angle: round-off is ~1e-15 rad; 1e-9 rad is margin.
    const ANGLE_TOL: f64 = 1e-9;
    /// Central differences with h = 1e-6 on unit-scale rays: truncation ~1e-10, cancellation
    /// ~1e-16 * 1e3 px / 1e-6 = 1e-7 px; compared relative to fx / |ray| (~300..5000 px).
    const JAC_REL_TOL: f64 = 1e-6;
    const FD_STEP: f64 = 1e-6;

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

    fn jacobian(cam: &Camera, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        match cam {
            Camera::KannalaBrandt(m) => m.project_jacobian(ray),
            Camera::Pinhole(m) => m.project_jacobian(ray),
        }
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
    }

    /// The sweep over every shipped camera: pixel and ray round trips at several depths, the
    /// principal point, rays past 90 degrees, outside the domain -> None, Jacobian vs central
    /// differences.
    #[test]
    fn every_shipped_camera_sweep() {
        for name in ["f195.toml", "f165.toml", "pers.toml"] {
            let cam = load(shipped(name)).unwrap();
            let [w, h] = cam.size();
            let (cx, cy, fx) = match &cam {
                Camera::KannalaBrandt(m) => (m.cx, m.cy, m.fx),
                Camera::Pinhole(m) => (m.cx, m.cy, m.fx),
            };

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
            assert!(checked > 60_000, "{checked}");

            // unproject(project(ray)) for rays over the field of view (past 90 deg for F195).
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

                        // Jacobian vs central differences.
                        if theta < half_fov {
                            let jac = jacobian(&cam, ray).unwrap();
                            for k in 0..3 {
                                let (mut p, mut m) = (ray, ray);
                                p[k] += FD_STEP * len;
                                m[k] -= FD_STEP * len;
                                let (pp, pm) = (cam.project(p).unwrap(), cam.project(m).unwrap());
                                for r in 0..2 {
                                    let fd = (pp[r] - pm[r]) / (2.0 * FD_STEP * len);
                                    assert!(
                                        (fd - jac[r][k]).abs() < JAC_REL_TOL * fx / len,
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
            assert_eq!(cam.unproject([cx, cy]), Some([0.0, 0.0, 1.0]));
            assert_eq!(cam.project([0.0, 0.0, 4.0]), Some([cx, cy]));

            // Rays past 90 degrees; outside the domain.
            let past = 100f64.to_radians();
            let past = cam.project([past.sin(), 0.0, past.cos()]);
            assert_eq!(cam.project([0.0, 0.0, -1.0]), None, "{name}");
            assert_eq!(cam.project([0.0, 0.0, 0.0]), None, "{name}");
            match &cam {
                Camera::KannalaBrandt(m) => {
                    assert!(past.is_some(), "{name}");
                    let edge = m.fx * m.distort(m.theta_max());
                    assert_eq!(cam.unproject([cx + 1.01 * edge, cy]), None, "{name}");
                }
                Camera::Pinhole(_) => {
                    assert_eq!(past, None);
                    assert_eq!(cam.project([0.3, 0.1, -1.0]), None);
                }
            }

            // Rescaling keeps the model and is undone by the inverse scale.
            let half = cam.rescaled([0.5, 0.5], PixelConvention::HalfPixel);
            assert_eq!(half.size(), [w / 2, h / 2]);
            assert_eq!(half.rescaled([2.0, 2.0], PixelConvention::HalfPixel), cam);
        }
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
}
