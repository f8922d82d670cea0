//! Cross-checks between models in their equivalence cases. No independent executable
//! implementation of the double sphere, (extended) unified or Scaramuzza models is available in
//! the project's Python environment, so each is checked against another model of this module,
//! computed by a different formula:
//!
//! - double sphere with `xi = 0` is the unified model with the same `alpha` (Usenko et al. 2018,
//!   Section 3.6); its unprojection (Eqs. 44-47) against Mei's closed form used by [`Unified`];
//! - extended unified with `beta = 1` is the unified model (Khomutenko et al. 2016; Usenko et al.
//!   Section 3.4): Eqs. 26-29 against Mei's form;
//! - unified with `alpha = 0` (and double sphere with `xi = alpha = 0`) is the pinhole camera;
//! - Scaramuzza with `f(rho) = -f + rho^2 / (4 f)` and an identity affine part is the unified
//!   model with `alpha = 0.5` (the para-catadioptric camera, Geyer and Daniilidis 2000): Mei's
//!   unprojection at `xi = 1` gives the ray `[2 m, 1 - |m|^2]` with `m = rho / (2 f)`, i.e.
//!   `[rho, f - rho^2 / (4 f)]`; this checks the Newton-based projection against a closed form.

use std::path::PathBuf;

use super::*;
use crate::vec3::{angle_to_axis, cross, dot};

/// The repository's shipped camera files (`data/cameras/`, two floors above this crate).
pub(super) fn cameras_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/cameras")
}

/// Different closed forms of the same map agree to round-off (~1e-15 relative); near the edge of
/// the domain the inverse loses up to ~1e-16 / (theta_max - theta); 1e-10 is margin for both.
const EQUIV_ANGLE_TOL: f64 = 1e-10;
/// Pixel agreement of projections computed by different formulas: round-off times ~1e3 px.
const EQUIV_PX_TOL: f64 = 1e-9;

/// The angle between two rays, radians (`atan2(|a x b|, a . b)`, accurate at small angles).
pub(super) fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    let c = cross(a, b);
    c[0].hypot(c[1]).hypot(c[2]).atan2(dot(a, b))
}

/// A 640x480 camera's intrinsics with `fx != fy` and a fractional principal point: the test
/// cameras of the unified family.
pub(super) fn vga() -> Intrinsics {
    Intrinsics::from_parts([300.0, 298.0, 320.5, 240.25], [640, 480])
}

/// Every ray at an angle in `thetas` to the optical axis and an azimuth in `phis` projects and
/// unprojects back to within `tol` radians: `|angle_to_axis(back) - theta|` plus the azimuth
/// error `|back_x ray_y - back_y ray_x|`. `what` names the camera in the failure.
pub(super) fn assert_round_trips<C: CameraModel>(
    cam: &C,
    thetas: impl IntoIterator<Item = f64>,
    phis: &[f64],
    tol: f64,
    what: &str,
) {
    for t in thetas {
        for &phi in phis {
            let ray = [t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()];
            let back = cam.unproject(cam.project(ray).unwrap()).unwrap();
            let err = (angle_to_axis(back) - t).abs() + (back[0] * ray[1] - back[1] * ray[0]).abs();
            assert!(err < tol, "{what} theta {t} phi {phi}: {err}");
        }
    }
}

/// Asserts that a Newton inverse converges everywhere it is used: over the normalised
/// coordinates `[(u - cx) / fx, (v - cy) / fy]` of every pixel `(u, v)` of the image of
/// `intrinsics`, `solve` (returning `(iterations, error)`) takes at most `max_steps` steps
/// (`measured`: the most seen, for the message) and its error stays below `tol`. Returns the
/// largest step count.
pub(super) fn assert_newton_on_every_pixel(
    intrinsics: &Intrinsics,
    solve: impl Fn([f64; 2]) -> (usize, f64),
    [max_steps, measured]: [usize; 2],
    tol: f64,
) -> usize {
    let (mut worst, mut worst_err) = (0, 0.0f64);
    for v in 0..intrinsics.height {
        for u in 0..intrinsics.width {
            let m = [
                (u as f64 - intrinsics.cx) / intrinsics.fx,
                (v as f64 - intrinsics.cy) / intrinsics.fy,
            ];
            let (iters, err) = solve(m);
            worst = worst.max(iters);
            worst_err = worst_err.max(err);
        }
    }
    assert!(
        worst <= max_steps,
        "Newton took {worst} steps (measured: {measured} at most)"
    );
    assert!(worst_err < tol, "worst error {worst_err}");
    worst
}

/// Asserts that every entry `[r][k]` of `jacobian`, the analytic Jacobian of a map `f` to 2-D
/// (a projection, a distortion) at `x`, is within `tol` of the central difference
/// `(f(x + h e_k)[r] - f(x - h e_k)[r]) / 2h`; `what` names `x` in the message.
pub(super) fn assert_matches_central_differences<const N: usize>(
    f: impl Fn([f64; N]) -> [f64; 2],
    x: [f64; N],
    h: f64,
    jacobian: &[[f64; N]; 2],
    tol: f64,
    what: &str,
) {
    for k in 0..N {
        let (mut a, mut b) = (x, x);
        a[k] += h;
        b[k] -= h;
        let (fa, fb) = (f(a), f(b));
        for r in 0..2 {
            let fd = (fa[r] - fb[r]) / (2.0 * h);
            assert!(
                (fd - jacobian[r][k]).abs() < tol,
                "{what} [{r}][{k}]: fd {fd} analytic {}",
                jacobian[r][k]
            );
        }
    }
}

/// `jacobian` (the model's `project_jacobian`) at each of `rays` against central differences of
/// `cam.project` (step 1e-6: ~1e-10 px/unit truncation, ~1e-7 cancellation, so 1e-5 absolute).
pub(super) fn assert_jacobian_matches_central_differences<C: CameraModel>(
    cam: &C,
    jacobian: impl Fn([f64; 3]) -> Option<[[f64; 3]; 2]>,
    rays: &[[f64; 3]],
) {
    for &ray in rays {
        let j = jacobian(ray).unwrap();
        let project = |r| cam.project(r).unwrap();
        assert_matches_central_differences(project, ray, 1e-6, &j, 1e-5, &format!("{ray:?}"));
    }
}

/// The authors' F195 calibration (CalibratedConvolutions, fisheye_calibration_FOV195.txt).
pub(super) fn f195() -> KannalaBrandt {
    kb(
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
    )
}

/// EuRoC MAV data set, cam0 `sensor.yaml` (Kalibr pinhole-radtan, k3 = 0), 752x480.
pub(super) fn euroc() -> PinholeRadTan {
    radtan(
        458.654,
        457.296,
        367.215,
        248.375,
        [-0.28340811, 0.07395907, 0.0],
        [0.00019359, 1.76187114e-05],
        752,
        480,
    )
}

/// A Kannala-Brandt camera from positional parameters, unchecked (some tests need a folding
/// polynomial).
#[allow(clippy::too_many_arguments)]
pub(super) fn kb(
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k: [f64; 4],
    width: usize,
    height: usize,
    fov_deg: f64,
) -> KannalaBrandt {
    KannalaBrandt::unchecked(
        Intrinsics::from_parts([fx, fy, cx, cy], [width, height]),
        k,
        fov_deg,
    )
}

/// A radial-tangential camera from positional parameters, unchecked.
#[allow(clippy::too_many_arguments)]
pub(super) fn radtan(
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    k: [f64; 3],
    p: [f64; 2],
    width: usize,
    height: usize,
) -> PinholeRadTan {
    PinholeRadTan::unchecked(
        Intrinsics::from_parts([fx, fy, cx, cy], [width, height]),
        [k[0], k[1], k[2], 0.0, 0.0, 0.0],
        p,
        0.0,
    )
}

fn unified(alpha: f64) -> Unified {
    let intrinsics = Intrinsics::from_parts([300.0, 290.0, 320.5, 240.25], [640, 480]);
    Unified::unchecked(intrinsics, alpha, 180.0)
}

/// Pixels on a grid covering the image and well beyond it.
fn pixel_grid() -> Vec<[f64; 2]> {
    let mut out = Vec::new();
    for i in -10..=30 {
        for j in -10..=30 {
            out.push([i as f64 * 32.0 + 0.25, j as f64 * 24.0 - 0.5]);
        }
    }
    out
}

/// Rays at angles up to `theta_max` (exclusive) in several azimuths.
fn ray_grid(theta_max: f64) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for i in 0..100 {
        let t = theta_max.min(std::f64::consts::PI * 0.999) * i as f64 / 100.0;
        for phi in [0.0f64, 0.7, 1.9, 3.3, 5.1] {
            out.push([t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()]);
        }
    }
    out
}

fn same_camera(a: &impl CameraModel, b: &impl CameraModel, theta_max: f64, what: &str) {
    let mut unprojected = 0;
    for px in pixel_grid() {
        match (a.unproject(px), b.unproject(px)) {
            (Some(ra), Some(rb)) => {
                assert!(
                    angle(ra, rb) < EQUIV_ANGLE_TOL,
                    "{what} {px:?}: {ra:?} vs {rb:?}"
                );
                unprojected += 1;
            }
            (None, None) => {}
            (ra, rb) => panic!("{what} {px:?}: {ra:?} vs {rb:?}"),
        }
    }
    assert!(
        unprojected > 500,
        "{what}: only {unprojected} pixels unprojected"
    );
    for ray in ray_grid(theta_max) {
        let (pa, pb) = (a.project(ray).unwrap(), b.project(ray).unwrap());
        let err = (pa[0] - pb[0]).hypot(pa[1] - pb[1]);
        assert!(err < EQUIV_PX_TOL, "{what} {ray:?}: {pa:?} vs {pb:?}");
    }
}

#[test]
fn double_sphere_with_xi_zero_is_the_unified_model() {
    for alpha in [0.0, 0.3, 0.5, 0.6, 0.8] {
        let u = unified(alpha);
        let ds = DoubleSphere::unchecked(*u, 0.0, alpha, u.fov_deg);
        assert!((ds.theta_max() - u.theta_max()).abs() < 1e-15);
        same_camera(&ds, &u, u.theta_max(), &format!("DS xi=0 alpha={alpha}"));
    }
}

#[test]
fn extended_unified_with_beta_one_is_the_unified_model() {
    for alpha in [0.0, 0.3, 0.5, 0.6, 0.8] {
        let u = unified(alpha);
        let e = ExtendedUnified::unchecked(*u, alpha, 1.0, u.fov_deg);
        assert!((e.theta_max() - u.theta_max()).abs() < 1e-15);
        same_camera(&e, &u, u.theta_max(), &format!("EUCM beta=1 alpha={alpha}"));
    }
}

#[test]
fn unified_with_alpha_zero_is_the_pinhole() {
    let u = unified(0.0);
    let p = Pinhole::new(*u).unwrap();
    same_camera(&u, &p, std::f64::consts::FRAC_PI_2 * 0.99, "UCM alpha=0");
    let ds = DoubleSphere::unchecked(*u, 0.0, 0.0, u.fov_deg);
    same_camera(&ds, &p, std::f64::consts::FRAC_PI_2 * 0.99, "DS xi=alpha=0");
    assert_eq!(u.project([0.1, 0.0, 0.0]), None);
}

#[test]
fn para_catadioptric_scaramuzza_is_the_unified_model_at_one_half() {
    let f = 150.0;
    let s = Scaramuzza::unchecked(
        vec![-f, 0.0, 1.0 / (4.0 * f)],
        vec![],
        [320.5, 240.25],
        [1.0, 0.0, 0.0],
        [640, 480],
        180.0,
    );
    let intrinsics = Intrinsics::from_parts([f, f, 320.5, 240.25], [640, 480]);
    let u = Unified::unchecked(intrinsics, 0.5, 180.0);
    // theta approaches pi only as rho -> infinity; the search stops at twice the diagonal
    // (1600 px, ~158.8 deg).
    let tm = s.theta_max();
    assert!((s.rho_max() - 1600.0).abs() < 1e-9, "{}", s.rho_max());
    assert!(tm > 150f64.to_radians(), "{}", tm.to_degrees());
    for ray in ray_grid(tm * 0.999) {
        let (ps, pu) = (s.project(ray).unwrap(), u.project(ray).unwrap());
        let err = (ps[0] - pu[0]).hypot(ps[1] - pu[1]);
        assert!(err < EQUIV_PX_TOL, "{ray:?}: {ps:?} vs {pu:?}");
    }
    for px in pixel_grid() {
        let (rs, ru) = (s.unproject(px).unwrap(), u.unproject(px).unwrap());
        assert!(angle(rs, ru) < EQUIV_ANGLE_TOL, "{px:?}");
    }
    // At rho = 2 f the para-catadioptric ray [rho, f - rho^2 / (4 f)] = [2 f, 0] is at 90 deg.
    let side = s.unproject([320.5 + 2.0 * f, 240.25]).unwrap();
    assert!((angle_to_axis(side) - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
}

#[test]
fn only_the_panorama_wraps() {
    let cams: Vec<Camera> = vec![
        Camera::Unified(unified(0.4)),
        Camera::Pinhole(
            Pinhole::new(Intrinsics::from_parts([1.0, 1.0, 0.0, 0.0], [2, 2])).unwrap(),
        ),
        Camera::Equirectangular(Equirectangular::new(64, 32).unwrap()),
    ];
    let wraps: Vec<bool> = cams.iter().map(|c| c.wraps_horizontally()).collect();
    assert_eq!(wraps, [false, false, true]);
}

#[test]
fn command_line_names_parse_and_list_the_choices() {
    use crate::camera::import::{Format, OpenCvModel};
    assert_eq!("paper".parse(), Ok(PixelConvention::Paper));
    assert_eq!(
        "x".parse::<PixelConvention>(),
        Err("unknown pixel convention `x` (expected half-pixel or paper)".to_string())
    );
    assert_eq!(
        "x".parse::<Format>(),
        Err(
            "unknown format `x` (expected kalibr, opencv, basalt, colmap, ocamcalib, ros or \
             orbslam3)"
                .to_string()
        )
    );
    assert_eq!(
        "x".parse::<OpenCvModel>(),
        Err("unknown OpenCV model `x` (expected fisheye or standard)".to_string())
    );
    // Each format's name round-trips: import::tests::formats_and_models_parse_from_their_names.
}
