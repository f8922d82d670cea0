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
//! [`CameraModel`] is used to project and unproject.

mod common;

use std::io::Write;

use calibconv::camera::{self, Camera, CameraModel};
use serde::Deserialize;

use common::{golden, read_text};

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

#[derive(Deserialize)]
struct Fixture {
    generator: String,
    cameras: Vec<FixtureCamera>,
}

#[derive(Deserialize)]
struct FixtureCamera {
    name: String,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k: [f64; 4],
    width: usize,
    height: usize,
    project: Projections,
    unproject: Unprojections,
}

#[derive(Deserialize)]
struct Projections {
    rays: Vec<[f64; 3]>,
    pixels: Vec<[f64; 2]>,
}

#[derive(Deserialize)]
struct Unprojections {
    pixels: Vec<[f64; 2]>,
    normalized: Vec<[f64; 2]>,
}

fn fixture() -> Fixture {
    let path = golden("opencv_fisheye.json");
    let fixture: Fixture = serde_json::from_str(&read_text(&path))
        .unwrap_or_else(|e| panic!("parsing {}: {e}", path.display()));
    assert!(
        fixture.generator.contains("OpenCV"),
        "{}",
        fixture.generator
    );
    assert_eq!(fixture.cameras.len(), CAMERAS, "cameras in the fixture");
    for cam in &fixture.cameras {
        let (p, u) = (&cam.project, &cam.unproject);
        assert_eq!(p.rays.len(), p.pixels.len(), "{}: rays vs pixels", cam.name);
        assert_eq!(
            u.pixels.len(),
            u.normalized.len(),
            "{}: pixels vs normalized",
            cam.name
        );
        assert!(
            p.rays.len() >= MIN_POINTS,
            "{}: {} rays",
            cam.name,
            p.rays.len()
        );
        assert!(
            u.pixels.len() >= MIN_POINTS,
            "{}: {} pixels",
            cam.name,
            u.pixels.len()
        );
    }
    fixture
}

/// The camera file text for a fixture camera. `fov_deg = 180`: the fixture only covers the front
/// hemisphere, and the loader checks that d(theta) increases up to fov_deg / 2 = 90 deg.
fn camera_file(cam: &FixtureCamera) -> String {
    let [k1, k2, k3, k4] = cam.k;
    // `{:?}` prints the shortest text that reads back to the same f64, always a valid TOML float.
    format!(
        "model = \"kannala-brandt\"\nwidth = {}\nheight = {}\nfov_deg = 180.0\n\
         fx = {:?}\nfy = {:?}\ncx = {:?}\ncy = {:?}\nk1 = {k1:?}\nk2 = {k2:?}\nk3 = {k3:?}\nk4 = {k4:?}\n",
        cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy
    )
}

/// Writes the fixture camera to a temporary camera file and reads it through the library.
fn load_fixture_camera(cam: &FixtureCamera) -> Camera {
    let mut file = tempfile::Builder::new()
        .suffix(".toml")
        .tempfile()
        .expect("temporary camera file");
    file.write_all(camera_file(cam).as_bytes()).unwrap();
    file.flush().unwrap();
    camera::load(file.path())
        .unwrap_or_else(|e| panic!("{}: loading the camera file: {e:#}", cam.name))
}

fn f195_file() -> std::path::PathBuf {
    std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/cameras/f195.toml")
}

/// Every camera to check: each fixture camera through a temporary file, and F195 also through the
/// shipped `data/cameras/f195.toml`.
fn cameras_under_test(fixture: &Fixture) -> Vec<(String, Camera, &FixtureCamera)> {
    let mut out = Vec::new();
    for cam in &fixture.cameras {
        out.push((
            format!("{} (temp file)", cam.name),
            load_fixture_camera(cam),
            cam,
        ));
        if cam.name == "F195" {
            let shipped = camera::load(f195_file()).expect("data/cameras/f195.toml");
            out.push(("F195 (data/cameras/f195.toml)".to_string(), shipped, cam));
        }
    }
    assert_eq!(out.len(), CAMERAS + 1, "F195 missing from the fixture");
    out
}

#[test]
fn projection_matches_opencv_project_points() {
    let fixture = fixture();
    let mut failures = Vec::new();
    for (label, cam, fx) in cameras_under_test(&fixture) {
        let mut worst = 0.0f64;
        for (i, (ray, want)) in fx.project.rays.iter().zip(&fx.project.pixels).enumerate() {
            let Some(got) = cam.project(*ray) else {
                failures.push(format!("{label} ray {i} {ray:?}: None, OpenCV {want:?}"));
                continue;
            };
            let err = (got[0] - want[0]).hypot(got[1] - want[1]);
            worst = worst.max(err);
            if err.is_nan() || err >= PROJECT_TOL_PX {
                failures.push(format!(
                    "{label} ray {i} {ray:?}: {got:?} vs OpenCV {want:?} ({err:.3e} px)"
                ));
            }
        }
        println!("{label}: worst projection error {worst:.3e} px");
    }
    assert!(
        failures.is_empty(),
        "{} projections differ from OpenCV beyond {PROJECT_TOL_PX:e} px:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn unprojection_matches_opencv_undistort_points() {
    let fixture = fixture();
    let mut failures = Vec::new();
    for (label, cam, fx) in cameras_under_test(&fixture) {
        let mut worst = 0.0f64;
        let pairs = fx.unproject.pixels.iter().zip(&fx.unproject.normalized);
        for (i, (px, want)) in pairs.enumerate() {
            let Some(ray) = cam.unproject(*px) else {
                failures.push(format!("{label} pixel {i} {px:?}: None, OpenCV {want:?}"));
                continue;
            };
            let norm = ray[0].hypot(ray[1]).hypot(ray[2]);
            if !((norm - 1.0).abs() < 1e-12 && ray[2] > 0.0) {
                failures.push(format!(
                    "{label} pixel {i} {px:?}: ray {ray:?} not a front unit ray"
                ));
                continue;
            }
            let got = [ray[0] / ray[2], ray[1] / ray[2]];
            let err = (got[0] - want[0]).hypot(got[1] - want[1]) / want[0].hypot(want[1]).max(1.0);
            worst = worst.max(err);
            if err.is_nan() || err >= UNPROJECT_REL_TOL {
                failures.push(format!(
                    "{label} pixel {i} {px:?}: {got:?} vs OpenCV {want:?} (rel {err:.3e})"
                ));
            }
        }
        println!("{label}: worst unprojection error {worst:.3e} (relative)");
    }
    assert!(
        failures.is_empty(),
        "{} unprojections differ from OpenCV beyond {UNPROJECT_REL_TOL:e}:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The fixture's F195 is the calibration shipped in `data/cameras/f195.toml`.
#[test]
fn f195_file_holds_the_fixture_calibration() {
    let fixture = fixture();
    let want = fixture
        .cameras
        .iter()
        .find(|c| c.name == "F195")
        .expect("F195 in the fixture");
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
        ("k1", kb.k[0], want.k[0]),
        ("k2", kb.k[1], want.k[1]),
        ("k3", kb.k[2], want.k[2]),
        ("k4", kb.k[3], want.k[3]),
    ];
    for (field, file, fixture) in pairs {
        assert!(
            close(file, fixture),
            "F195 {field}: file {file:e}, fixture {fixture:e}"
        );
    }
    assert_eq!([kb.width, kb.height], [want.width, want.height]);
}
