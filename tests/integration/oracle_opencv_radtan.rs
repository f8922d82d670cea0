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
//! file format, the loader and the model are tested together; only `CameraModel` is used (see
//! `common::opencv`).

use calibconv::camera;
use serde::Deserialize;

use crate::common;
use crate::common::opencv::{self, Distortion};

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

/// The radial `k1, k2, k3` and tangential `p1, p2` coefficients.
#[derive(Deserialize)]
struct RadTan {
    k: [f64; 3],
    p: [f64; 2],
}

impl Distortion for RadTan {
    const MODEL: &'static str = "pinhole-radtan";
    fn fields(&self) -> String {
        let ([k1, k2, k3], [p1, p2]) = (self.k, self.p);
        format!("k1 = {k1:?}\nk2 = {k2:?}\np1 = {p1:?}\np2 = {p2:?}\nk3 = {k3:?}\n")
    }
}

fn fixture() -> opencv::Fixture<RadTan> {
    opencv::read_fixture("opencv_radtan.json", CAMERAS, MIN_POINTS)
}

opencv::fixture_tests!(opencv::cases(&fixture()), PROJECT_TOL_PX, UNPROJECT_REL_TOL);

#[test]
fn euroc_file_holds_the_fixture_calibration() {
    let shipped = camera::load(common::root().join("data/cameras/radtan_example.toml")).unwrap();
    assert_eq!(shipped, fixture().camera("EuRoC cam0").load());
}
