//! Kannala-Brandt cameras read through `calibconv::camera::load` against OpenCV's fisheye model.
//!
//! Fixture: `tests/golden/opencv_fisheye.json`, written by `tools/make_fixtures.py` (see
//! `tests/golden/README.md`) with `cv2.fisheye.projectPoints` (rays -> pixels, `rvec = tvec = 0`)
//! and `cv2.fisheye.undistortPoints` (pixels -> normalized `(x/z, y/z)`), in float64. OpenCV works
//! with `x/z`, so every fixture ray is in front of the camera (theta <= 85 deg for projection,
//! <= 80 deg for undistortion, where OpenCV's solver converges).
//!
//! Each fixture camera is written as a camera file and read with the library's loader, so the
//! file format, the loader and the model are tested together; only the trait
//! `CameraModel` is used to project and unproject (see `common::opencv`).

use calibconv::camera::{self, Camera};
use serde::Deserialize;

use crate::common;
use crate::common::opencv::{self, Distortion};

/// Projection: OpenCV and the library evaluate the same polynomial in float64 and differ only in
/// round-off (atan(r) vs atan2(rho, z), evaluation order), ~1e-13 px at these radii; 1e-9 px is
/// margin, and any modelling difference (a swapped fx/cx, a missing term) is >= 1e-3 px.
const PROJECT_TOL_PX: f64 = 1e-9;
/// Unprojection, on `(x/z, y/z)` relative to `max(|(x/z, y/z)|, 1)`: both solve d(theta) = r_d by
/// Newton to round-off (~1e-15 rad; library EPS 1e-12 rad on a quadratically shrinking step,
/// OpenCV eps 1e-14), and tan(theta) amplifies that by 1/cos^2 <= 33 at 80 deg: ~1e-14; 1e-9 is
/// margin, and a wrong model or a solver stopped early is far above it.
const UNPROJECT_REL_TOL: f64 = 1e-9;
/// Each camera in the fixture has at least this many points of each kind (a truncated or empty
/// fixture must fail, not pass vacuously).
const MIN_POINTS: usize = 150;
/// Number of cameras the fixture holds (F195 and a strongly distorted test camera).
const CAMERAS: usize = 2;
/// serde_json parses floats "best effort" (without its `float_roundtrip` feature, the last bit
/// may differ from Rust's `str::parse`), so parameters read from JSON and from TOML may differ by
/// an ulp or two: 1e-15 relative.
const PARAM_REL_TOL: f64 = 1e-15;

/// Kannala-Brandt's four coefficients.
#[derive(Deserialize)]
struct KannalaBrandt {
    k: [f64; 4],
}

impl Distortion for KannalaBrandt {
    const MODEL: &'static str = "kannala-brandt";
    /// `fov_deg = 180`: the fixture only covers the front hemisphere, and the loader checks that
    /// d(theta) increases up to fov_deg / 2 = 90 deg.
    fn fields(&self) -> String {
        let [k1, k2, k3, k4] = self.k;
        format!("fov_deg = 180.0\nk1 = {k1:?}\nk2 = {k2:?}\nk3 = {k3:?}\nk4 = {k4:?}\n")
    }
}

type Fixture = opencv::Fixture<KannalaBrandt>;

fn fixture() -> Fixture {
    opencv::read_fixture("opencv_fisheye.json", CAMERAS, MIN_POINTS)
}

fn f195_file() -> std::path::PathBuf {
    common::root().join("data/cameras/f195.toml")
}

/// Every camera to check: each fixture camera through a temporary file, and F195 also through the
/// shipped `data/cameras/f195.toml`.
fn cameras_under_test(fixture: &Fixture) -> Vec<opencv::Case<'_, KannalaBrandt>> {
    let mut out = opencv::cases(fixture);
    let f195 = fixture.cameras.iter().find(|c| c.name == "F195");
    if let Some(cam) = f195 {
        let shipped = camera::load(f195_file()).expect("data/cameras/f195.toml");
        out.push(("F195 (data/cameras/f195.toml)".to_string(), shipped, cam));
    }
    assert_eq!(out.len(), CAMERAS + 1, "F195 missing from the fixture");
    out
}

opencv::fixture_tests!(
    cameras_under_test(&fixture()),
    PROJECT_TOL_PX,
    UNPROJECT_REL_TOL
);

#[test]
fn f195_file_holds_the_fixture_calibration() {
    let fixture = fixture();
    let want = fixture.camera("F195");
    let Camera::KannalaBrandt(kb) = camera::load(f195_file()).expect("data/cameras/f195.toml")
    else {
        panic!("data/cameras/f195.toml is not a Kannala-Brandt camera");
    };
    let close = |a: f64, b: f64| (a - b).abs() <= PARAM_REL_TOL * b.abs();
    let pairs = [
        ("fx", kb.fx, want.fx),
        ("fy", kb.fy, want.fy),
        ("cx", kb.cx, want.cx),
        ("cy", kb.cy, want.cy),
        ("k1", kb.k[0], want.distortion.k[0]),
        ("k2", kb.k[1], want.distortion.k[1]),
        ("k3", kb.k[2], want.distortion.k[2]),
        ("k4", kb.k[3], want.distortion.k[3]),
    ];
    for (field, file, fixture) in pairs {
        assert!(
            close(file, fixture),
            "F195 {field}: file {file:e}, fixture {fixture:e}"
        );
    }
    assert_eq!([kb.width, kb.height], [want.width, want.height]);
}
