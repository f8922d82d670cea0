//! The OpenCV camera fixtures (`tests/golden/opencv_*.json`, written by `tools/make_fixtures.py`)
//! and the checks that `oracle_opencv.rs` and `oracle_opencv_radtan.rs` run on them.
//!
//! A fixture camera is written as a camera file and read with the library's loader, so the file
//! format, the loader and the model are tested together; only [`CameraModel`] is used to project
//! and unproject.

use std::io::Write;

use calibconv::camera::{self, Camera, CameraModel};
use serde::de::DeserializeOwned;
use serde::Deserialize;

use super::{golden, read_text};

/// A fixture: which tool made it, and its cameras with OpenCV's results.
#[derive(Deserialize)]
#[serde(bound = "D: Distortion")]
pub struct Fixture<D> {
    pub generator: String,
    pub cameras: Vec<FixtureCamera<D>>,
}

/// One camera: its calibration and what OpenCV computes with it.
#[derive(Deserialize)]
#[serde(bound = "D: Distortion")]
pub struct FixtureCamera<D> {
    pub name: String,
    // In camera-file order.
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// The model's own coefficients.
    #[serde(flatten)]
    pub distortion: D,
    pub project: Projections,
    pub unproject: Unprojections,
}

/// Rays and the pixels OpenCV projects them to (`rvec = tvec = 0`).
#[derive(Deserialize)]
pub struct Projections {
    pub rays: Vec<[f64; 3]>,
    pub pixels: Vec<[f64; 2]>,
}

/// Pixels and the normalized `(x/z, y/z)` OpenCV undistorts them to.
#[derive(Deserialize)]
pub struct Unprojections {
    pub pixels: Vec<[f64; 2]>,
    pub normalized: Vec<[f64; 2]>,
}

/// A camera model's coefficients in a fixture, and how a camera file writes them.
pub trait Distortion: DeserializeOwned {
    /// The camera file's `model`.
    const MODEL: &'static str;
    /// The camera file's lines for the model's own fields (`key = value\n` each).
    fn fields(&self) -> String;
}

/// A camera under test: a label for messages, the camera the library read, and the fixture
/// camera whose OpenCV results it must reproduce.
pub type Case<'a, D> = (String, Camera, &'a FixtureCamera<D>);

/// Reads `tests/golden/NAME` and checks that OpenCV made it, that it holds `cameras` cameras
/// and that each has matching inputs and outputs, at least `min_points` of each kind (a
/// truncated or empty fixture must fail, not pass vacuously).
pub fn read_fixture<D: Distortion>(name: &str, cameras: usize, min_points: usize) -> Fixture<D> {
    let path = golden(name);
    let fixture: Fixture<D> = serde_json::from_str(&read_text(&path))
        .unwrap_or_else(|e| panic!("parsing {}: {e}", path.display()));
    assert!(
        fixture.generator.contains("OpenCV"),
        "{}",
        fixture.generator
    );
    assert_eq!(fixture.cameras.len(), cameras, "cameras in the fixture");
    for cam in &fixture.cameras {
        let (p, u) = (&cam.project, &cam.unproject);
        assert_eq!(p.rays.len(), p.pixels.len(), "{}: rays vs pixels", cam.name);
        assert_eq!(
            u.pixels.len(),
            u.normalized.len(),
            "{}: pixels vs normalized",
            cam.name
        );
        for (what, n) in [("rays", p.rays.len()), ("pixels", u.pixels.len())] {
            assert!(n >= min_points, "{}: {n} {what}", cam.name);
        }
    }
    fixture
}

impl<D> Fixture<D> {
    /// The camera called `name`.
    ///
    /// # Panics
    /// If the fixture has no such camera.
    pub fn camera(&self, name: &str) -> &FixtureCamera<D> {
        let found = self.cameras.iter().find(|c| c.name == name);
        found.unwrap_or_else(|| panic!("no camera {name:?} in the fixture"))
    }
}

impl<D: Distortion> FixtureCamera<D> {
    /// The camera file text for this camera. `{:?}` prints the shortest text that reads back to
    /// the same f64, always a valid TOML float.
    pub fn camera_file(&self) -> String {
        format!(
            "model = \"{}\"\nwidth = {}\nheight = {}\nfx = {:?}\nfy = {:?}\ncx = {:?}\ncy = {:?}\n{}",
            D::MODEL,
            self.width,
            self.height,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            self.distortion.fields()
        )
    }

    /// Writes [`Self::camera_file`] to a temporary file and reads it through the library.
    pub fn load(&self) -> Camera {
        let mut file = tempfile::Builder::new()
            .suffix(".toml")
            .tempfile()
            .expect("temporary camera file");
        file.write_all(self.camera_file().as_bytes()).unwrap();
        file.flush().unwrap();
        camera::load(file.path())
            .unwrap_or_else(|e| panic!("{}: loading the camera file: {e:#}", self.name))
    }
}

/// Every fixture camera, read through a temporary camera file.
pub fn cases<D: Distortion>(fixture: &Fixture<D>) -> Vec<Case<'_, D>> {
    let cams = fixture.cameras.iter();
    cams.map(|c| (format!("{} (temp file)", c.name), c.load(), c))
        .collect()
}

/// One point compared: the input, OpenCV's result, and the library's result with its error
/// against OpenCV's, or why there is none to compare.
type Compared = (String, [f64; 2], Result<([f64; 2], f64), String>);

/// Panics, listing each failure, unless every case projects every fixture ray to OpenCV's pixel
/// within `tol_px` pixels.
pub fn check_projections<D>(cases: &[Case<'_, D>], tol_px: f64) {
    judge("projection", " px", tol_px, cases, |cam, fx| {
        let pairs = fx.project.rays.iter().zip(&fx.project.pixels);
        let compare = |(ray, want): (&[f64; 3], &[f64; 2])| -> Compared {
            let got = cam.project(*ray).ok_or_else(|| "None".to_string());
            let err = |got: [f64; 2]| (got, (got[0] - want[0]).hypot(got[1] - want[1]));
            (format!("ray {ray:?}"), *want, got.map(err))
        };
        pairs.map(compare).collect()
    });
}

/// Panics, listing each failure, unless every case unprojects every fixture pixel to a unit ray
/// in front of the camera whose `(x/z, y/z)` is OpenCV's within `rel_tol` of
/// `max(|(x/z, y/z)|, 1)`.
pub fn check_unprojections<D>(cases: &[Case<'_, D>], rel_tol: f64) {
    judge("unprojection", " rel", rel_tol, cases, |cam, fx| {
        let pairs = fx.unproject.pixels.iter().zip(&fx.unproject.normalized);
        let compare = |(px, want): (&[f64; 2], &[f64; 2])| -> Compared {
            (format!("pixel {px:?}"), *want, unproject(cam, *px, *want))
        };
        pairs.map(compare).collect()
    });
}

/// The library's `(x/z, y/z)` of pixel `px` and its error relative to `max(|want|, 1)`, or why
/// there is none (no ray, or not a unit ray in front of the camera).
fn unproject(cam: &Camera, px: [f64; 2], want: [f64; 2]) -> Result<([f64; 2], f64), String> {
    let ray = cam.unproject(px).ok_or("None")?;
    let norm = ray[0].hypot(ray[1]).hypot(ray[2]);
    if !((norm - 1.0).abs() < 1e-12 && ray[2] > 0.0) {
        return Err(format!("ray {ray:?} not a front unit ray"));
    }
    let got = [ray[0] / ray[2], ray[1] / ray[2]];
    let err = (got[0] - want[0]).hypot(got[1] - want[1]) / want[0].hypot(want[1]).max(1.0);
    Ok((got, err))
}

/// Runs `compare` on every case and fails, listing every point whose comparison failed or
/// whose error is NaN or `>= tol`. `what` names the comparison and `unit` its error in messages.
fn judge<D>(
    what: &str,
    unit: &str,
    tol: f64,
    cases: &[Case<'_, D>],
    compare: impl Fn(&Camera, &FixtureCamera<D>) -> Vec<Compared>,
) {
    let mut failures = Vec::new();
    for (label, cam, fx) in cases {
        let mut worst = 0.0f64;
        for (i, (input, want, result)) in compare(cam, fx).into_iter().enumerate() {
            let at = format!("{label} {input} (#{i})");
            match result {
                Err(why) => failures.push(format!("{at}: {why}, OpenCV {want:?}")),
                Ok((got, err)) => {
                    worst = worst.max(err);
                    if err.is_nan() || err >= tol {
                        let e = format!("{err:.3e}{unit}");
                        failures.push(format!("{at}: {got:?} vs OpenCV {want:?} ({e})"));
                    }
                }
            }
        }
        println!("{label}: worst {what} error {worst:.3e}{unit}");
    }
    assert!(
        failures.is_empty(),
        "{} {what}s differ from OpenCV beyond {tol:e}{unit}:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The two tests of a fixture: `projection_matches_opencv_project_points` and
/// `unprojection_matches_opencv_undistort_points`, on the cases `cases` evaluates to, within
/// the tolerances `project_tol_px` and `unproject_rel_tol`.
#[allow(unused_macros)]
macro_rules! fixture_tests {
    ($cases:expr, $project_tol_px:expr, $unproject_rel_tol:expr) => {
        #[test]
        fn projection_matches_opencv_project_points() {
            common::opencv::check_projections(&$cases, $project_tol_px);
        }

        #[test]
        fn unprojection_matches_opencv_undistort_points() {
            common::opencv::check_unprojections(&$cases, $unproject_rel_tol);
        }
    };
}
#[allow(unused_imports)]
pub(crate) use fixture_tests;
