//! Pinhole cameras with radial-tangential distortion, read through `calibconv::camera::load`,
//! against OpenCV's standard model.
//!
//! Fixture: `tests/golden/opencv_radtan.json`, written by `tools/make_fixtures.py` (see
//! `tests/golden/README.md`) with `cv2.projectPoints` (rays -> pixels, `rvec = tvec = 0`,
//! `D = [k1, k2, p1, p2, k3]`) and `cv2.undistortPoints` run to convergence (criteria
//! `COUNT | EPS, 100, 1e-14`; pixels -> normalized `(x/z, y/z)`), in float64: rays within 40 deg
//! of the axis, pixels anywhere in the image. Two cameras: EuRoC cam0 (`k3 = 0`, the shipped
//! `data/cameras/radtan_example.toml`) and a made-up camera with all five coefficients non-zero.
//!
//! Each fixture camera is written as a camera file and read with the library's loader, so the
//! file format, the loader and the model are tested together; only [`CameraModel`] is used.

mod common;

use std::io::Write;

use calibconv::camera::{self, Camera, CameraModel};
use serde::Deserialize;

use common::{golden, read_text};

/// Projection: both evaluate the same polynomial in float64 (round-off ~1e-13 px); 1e-9 px is
/// margin, and a modelling slip (p1 and p2 swapped, k3 on r^4) moves pixels by >= 1e-3 px.
const PROJECT_TOL_PX: f64 = 1e-9;
/// Unprojection on `(x/z, y/z)`, relative to `max(|(x/z, y/z)|, 1)`: OpenCV's fixed-point
/// iteration stops at a 1e-14 change, the library's Newton at a 1e-12 step with quadratic
/// convergence (its actual error is round-off); both ~1e-15 in practice, 1e-10 is margin.
const UNPROJECT_REL_TOL: f64 = 1e-10;
/// At least this many points of each kind per camera (a truncated fixture must fail).
const MIN_POINTS: usize = 150;
/// Cameras in the fixture.
const CAMERAS: usize = 2;

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
    k: [f64; 3],
    p: [f64; 2],
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
    let path = golden("opencv_radtan.json");
    let fixture: Fixture = serde_json::from_str(&read_text(&path))
        .unwrap_or_else(|e| panic!("parsing {}: {e}", path.display()));
    assert!(
        fixture.generator.contains("OpenCV"),
        "{}",
        fixture.generator
    );
    assert_eq!(fixture.cameras.len(), CAMERAS);
    for cam in &fixture.cameras {
        assert_eq!(cam.project.rays.len(), cam.project.pixels.len());
        assert_eq!(cam.unproject.pixels.len(), cam.unproject.normalized.len());
        assert!(cam.project.rays.len() >= MIN_POINTS, "{}", cam.name);
        assert!(cam.unproject.pixels.len() >= MIN_POINTS, "{}", cam.name);
    }
    fixture
}

/// The fixture camera as a camera file, read by the library.
fn load(cam: &FixtureCamera) -> Camera {
    let [k1, k2, k3] = cam.k;
    let [p1, p2] = cam.p;
    let text = format!(
        "model = \"pinhole-radtan\"\nwidth = {}\nheight = {}\nfx = {:?}\nfy = {:?}\ncx = {:?}\n\
         cy = {:?}\nk1 = {k1:?}\nk2 = {k2:?}\np1 = {p1:?}\np2 = {p2:?}\nk3 = {k3:?}\n",
        cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy
    );
    let mut file = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
    file.write_all(text.as_bytes()).unwrap();
    file.flush().unwrap();
    camera::load(file.path()).unwrap_or_else(|e| panic!("{}: {e:#}", cam.name))
}

#[test]
fn projection_matches_opencv_project_points() {
    let mut failures = Vec::new();
    for cam in &fixture().cameras {
        let model = load(cam);
        let mut worst = 0.0f64;
        for (ray, want) in cam.project.rays.iter().zip(&cam.project.pixels) {
            let Some(got) = model.project(*ray) else {
                failures.push(format!("{} {ray:?}: None, OpenCV {want:?}", cam.name));
                continue;
            };
            let err = (got[0] - want[0]).hypot(got[1] - want[1]);
            worst = worst.max(err);
            if err.is_nan() || err >= PROJECT_TOL_PX {
                failures.push(format!("{} {ray:?}: {got:?} vs {want:?}", cam.name));
            }
        }
        println!("{}: worst projection error {worst:.3e} px", cam.name);
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn unprojection_matches_opencv_undistort_points() {
    let mut failures = Vec::new();
    for cam in &fixture().cameras {
        let model = load(cam);
        let mut worst = 0.0f64;
        for (px, want) in cam.unproject.pixels.iter().zip(&cam.unproject.normalized) {
            let Some(ray) = model.unproject(*px) else {
                failures.push(format!("{} {px:?}: None, OpenCV {want:?}", cam.name));
                continue;
            };
            let got = [ray[0] / ray[2], ray[1] / ray[2]];
            let err = (got[0] - want[0]).hypot(got[1] - want[1]) / want[0].hypot(want[1]).max(1.0);
            worst = worst.max(err);
            if err.is_nan() || err >= UNPROJECT_REL_TOL {
                failures.push(format!(
                    "{} {px:?}: {got:?} vs {want:?} ({err:.3e})",
                    cam.name
                ));
            }
        }
        println!(
            "{}: worst unprojection error {worst:.3e} (relative)",
            cam.name
        );
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The fixture's EuRoC camera is the shipped `data/cameras/radtan_example.toml`.
#[test]
fn euroc_file_holds_the_fixture_calibration() {
    let fixture = fixture();
    let euroc = fixture
        .cameras
        .iter()
        .find(|c| c.name == "EuRoC cam0")
        .unwrap();
    let shipped = camera::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/cameras/radtan_example.toml"
    ))
    .unwrap();
    assert_eq!(shipped, load(euroc));
}
