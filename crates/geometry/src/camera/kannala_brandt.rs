//! The Kannala-Brandt fisheye model in its OpenCV-fisheye / Basalt `kb4` form, extended past
//! 90 degrees (paper Section 3.1, Eq. 1).
//!
//! For a ray `[x, y, z]` (camera frame: x right, y down, z forward):
//!
//! ```text
//! theta   = atan2(sqrt(x^2 + y^2), z)          angle to the optical axis, in [0, pi]
//! phi     = atan2(y, x)                        azimuth
//! d(theta) = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
//! u = fx d(theta) cos(phi) + cx
//! v = fy d(theta) sin(phi) + cy
//! ```
//!
//! Taking `theta` from `atan2` (not `atan(r / z)` on the `z = 1` plane as OpenCV does) lets rays
//! behind the image plane (`theta > 90 deg`, `z < 0`) project: a 195 degree lens needs them.
//!
//! The model is only invertible where `d` increases: its valid domain is
//! `theta in [0, theta_max]` with `theta_max = min(pi, first theta where d'(theta) <= 0)`,
//! computed once by [`KannalaBrandt::new`]. Pixels are `[u, v]` = (column, row) with the centre of
//! the top-left pixel at `(0, 0)`; angles are radians (the file's `fov_deg` is the one exception).

use std::f64::consts::PI;

use super::intrinsics::{deref_intrinsics, eq_by_fields};
use super::schema::{checked, raw_camera_file, CameraFile, Checked, Invalid};
use super::solve::{increasing_roots, last_ok};
#[cfg(doc)]
use super::solve::increasing_root;
use super::{Camera, CameraModel, Intrinsics, PixelConvention};

/// Convergence threshold on the Newton (or bisection) step, in radians: `fx * EPS` is about
/// 3e-10 px for the shipped lenses, yet it stays well above the ~1e-15 rad round-off floor of
/// `d(theta)`, so the test can actually fire.
pub const EPS: f64 = 1e-12;

/// The largest residual `|d(theta) - r_d|` (normalised units) a solved angle may leave: times a
/// focal length up to 1e4 px it is 1e-6 px, the accuracy the imports are checked to; a
/// converged Newton leaves ~1e-15.
pub const RESIDUAL_TOL: f64 = 1e-10;

/// Grid points used to scan `d'(theta)` over `[0, pi]` for its first non-positive value (step
/// about 3e-4 rad; a sign change between two grid points narrower than that would be missed, which
/// no realistic degree-9 lens polynomial produces).
const SCAN_STEPS: usize = 10_000;

/// A Kannala-Brandt (OpenCV-fisheye polynomial) camera.
///
/// Build it with [`KannalaBrandt::new`], which checks the parameters and finds the monotonic
/// range `theta_max` of the polynomial. The fields are public for reading (the intrinsics
/// through `Deref`, `cam.fx`); to change `k`, build a new camera with `new` so that `theta_max`
/// follows. Equality compares the parameters only (`theta_max` is a function of `k`).
#[derive(Clone, Debug)]
pub struct KannalaBrandt {
    intrinsics: Intrinsics,
    /// Polynomial coefficients `[k1, k2, k3, k4]` of `d(theta)`.
    pub k: [f64; 4],
    /// Full field of view of the lens, in degrees (as declared by the calibration).
    pub fov_deg: f64,
    /// End of the monotonic range of `d`, in radians (see [`KannalaBrandt::theta_max`]).
    theta_max: f64,
}

deref_intrinsics!(KannalaBrandt);

eq_by_fields!(KannalaBrandt: intrinsics, k, fov_deg);

raw_camera_file! {
    /// A Kannala-Brandt camera file as written.
    fisheye struct Raw {
        k1: f64,
        k2: f64,
        k3: f64,
        k4: f64,
    }
}

impl CameraFile for KannalaBrandt {
    const MODEL: &'static str = "kannala-brandt";
    type Raw = Raw;
    fn fields(&self) -> Vec<(&'static str, f64)> {
        let [k1, k2, k3, k4] = self.k;
        let params = [("k1", k1), ("k2", k2), ("k3", k3), ("k4", k4)];
        self.intrinsics.with_fov(self.fov_deg, &params)
    }
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        KannalaBrandt::new(r.intrinsics(), [r.k1, r.k2, r.k3, r.k4], r.fov_deg)
    }
}

impl KannalaBrandt {
    /// A checked camera (see [`KannalaBrandt::validate`]); computes `theta_max` (see
    /// [`KannalaBrandt::theta_max`]).
    pub fn new(intrinsics: Intrinsics, k: [f64; 4], fov_deg: f64) -> Result<Self, Invalid> {
        checked(Self::unchecked(intrinsics, k, fov_deg), Self::validate)
    }

    /// The camera without the checks: for rescaling a checked camera and for probing a model's
    /// domain before its field of view is known.
    pub(crate) fn unchecked(intrinsics: Intrinsics, k: [f64; 4], fov_deg: f64) -> Self {
        let mut cam = KannalaBrandt {
            intrinsics,
            k,
            fov_deg,
            theta_max: 0.0,
        };
        cam.theta_max = cam.find_theta_max();
        cam
    }

    /// Every float finite, the intrinsics ([`Intrinsics::validate`]), `0 < fov_deg < 360`, and
    /// a polynomial that increases on `[0, fov_deg / 2]`; the error names the field.
    pub fn validate(&self) -> Checked {
        self.intrinsics
            .validate_fisheye(&self.fields(), self.fov_deg)?;
        let half_fov = self.fov_deg / 2.0;
        if !self.is_monotonic_to(half_fov.to_radians()) {
            return Err(Invalid::new(
                "k1..k4",
                format!(
                    "d(theta) stops increasing at theta = {:.3} deg, before fov_deg/2 = {:.3} deg",
                    self.theta_max().to_degrees(),
                    half_fov
                ),
            ));
        }
        Ok(())
    }

    /// `d(theta) = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`: the distance
    /// from the principal point, in focal-length units, of a ray at angle `theta` (radians) to the
    /// optical axis.
    pub fn distort(&self, theta: f64) -> f64 {
        let [k1, k2, k3, k4] = self.k;
        let t2 = theta * theta;
        theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    }

    /// `d'(theta) = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8`.
    pub fn distort_derivative(&self, theta: f64) -> f64 {
        let [k1, k2, k3, k4] = self.k;
        let t2 = theta * theta;
        1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    }

    /// End of the valid domain, in radians: `theta_max = min(pi, first theta > 0 where
    /// d'(theta) <= 0)`. Rays with `theta > theta_max` do not project and pixels with
    /// `r_d > d(theta_max)` do not unproject.
    pub fn theta_max(&self) -> f64 {
        self.theta_max
    }

    /// Whether `d` increases strictly on `[0, theta]` (radians), i.e. `theta <= theta_max`.
    pub fn is_monotonic_to(&self, theta: f64) -> bool {
        theta.is_finite() && theta <= self.theta_max
    }

    /// Scans `d'` on a grid of [`SCAN_STEPS`] points over `[0, pi]`; at the first point where
    /// `d' > 0` fails (non-positive or NaN), bisects between it and the previous point.
    fn find_theta_max(&self) -> f64 {
        let increasing = |t: f64| self.distort_derivative(t) > 0.0;
        if !increasing(0.0) {
            return 0.0; // only reachable with non-finite coefficients
        }
        let step = PI / SCAN_STEPS as f64;
        let grid = (1..=SCAN_STEPS).map(|i| if i == SCAN_STEPS { PI } else { i as f64 * step });
        last_ok(increasing, 0.0, grid).unwrap_or(PI)
    }

    /// Solves `d(theta) = r_d` for `theta in [0, theta_max]` with the shared safeguarded Newton
    /// ([`increasing_root`]: `theta <- theta - (d(theta) - r_d) / d'(theta)`, bisecting whenever
    /// Newton would leave the bracket), converged when `|step| < EPS`. Returns
    /// `(theta, iterations)`, or `None` without convergence in
    /// [`MAX_ITER`](super::solve::MAX_ITER) steps or for `r_d` outside `[0, d(theta_max)]`.
    /// (`unproject` solves four at a time; the tests count this one's iterations.)
    #[cfg(test)]
    pub(crate) fn solve_theta(&self, r_d: f64) -> Option<(f64, usize)> {
        let [theta] = self.solve_thetas([r_d], [true]);
        theta
    }

    /// [`KannalaBrandt::solve_theta`] for the radii `r_d[l]` with `solve[l]` (the others give
    /// `None`), their Newton iterations in lockstep ([`increasing_roots`]): the same bits as one
    /// at a time.
    fn solve_thetas<const L: usize>(
        &self,
        r_d: [f64; L],
        solve: [bool; L],
    ) -> [Option<(f64, usize)>; L] {
        let hi = self.theta_max;
        let d_hi = self.distort(hi);
        let in_range: [bool; L] = std::array::from_fn(|l| solve[l] && r_d[l] >= 0.0 && r_d[l] <= d_hi);
        // d(theta) ~ theta for realistic lenses: r_d itself is an excellent first guess.
        let g = |l: usize, t: f64| (self.distort(t) - r_d[l], self.distort_derivative(t));
        let newton = std::array::from_fn(|l| in_range[l] && r_d[l] != 0.0);
        let mut thetas = increasing_roots(g, [[0.0, hi]; L], r_d, newton, [EPS, RESIDUAL_TOL]);
        for l in 0..L {
            if in_range[l] && r_d[l] == 0.0 {
                thetas[l] = Some((0.0, 0));
            }
        }
        thetas
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`] at `ray`, or `None`
    /// where `project` is `None`.
    ///
    /// With `n = |ray|`, `s = sin(theta)`, `c = cos(theta)`, `cp = cos(phi)`, `sp = sin(phi)`:
    ///
    /// ```text
    /// du/dx = fx / n (sp^2 d/s + cp^2 d' c)    du/dy = fx / n cp sp (d' c - d/s)    du/dz = -fx / n s cp d'
    /// dv/dx = fy / n cp sp (d' c - d/s)        dv/dy = fy / n (cp^2 d/s + sp^2 d' c)    dv/dz = -fy / n s sp d'
    /// ```
    ///
    /// On the optical axis (`theta = 0`) `d/s = d'(0) = 1` and `phi` is taken as 0.
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        let rho = x.hypot(y);
        let n = rho.hypot(z);
        let theta = rho.atan2(z);
        let (s, c) = theta.sin_cos();
        let (cp, sp) = if rho > 0.0 {
            (x / rho, y / rho)
        } else {
            (1.0, 0.0)
        };
        let d = self.distort(theta);
        let dd = self.distort_derivative(theta);
        let d_over_s = if s > 0.0 { d / s } else { 1.0 };
        let cross = cp * sp * (dd * c - d_over_s);
        Some([
            [
                self.fx / n * (sp * sp * d_over_s + cp * cp * dd * c),
                self.fx / n * cross,
                -self.fx / n * s * cp * dd,
            ],
            [
                self.fy / n * cross,
                self.fy / n * (cp * cp * d_over_s + sp * sp * dd * c),
                -self.fy / n * s * sp * dd,
            ],
        ])
    }
}

impl KannalaBrandt {
    /// [`CameraModel::unproject`] of `L` pixels, their Newton iterations in lockstep
    /// ([`KannalaBrandt::solve_thetas`]), so that the CPU overlaps their chains of dependent
    /// operations: with `r_d = sqrt(((u - cx) / fx)^2 + ((v - cy) / fy)^2)`, non-finite radii
    /// fail, the principal point is the optical axis, and otherwise `d(theta) = r_d` gives
    /// `[sin(theta) cos(phi), sin(theta) sin(phi), cos(theta)]`.
    fn unproject_lanes<const L: usize>(&self, px: [[f64; 2]; L]) -> [Option<[f64; 3]>; L] {
        let m = px.map(|[u, v]| {
            let mx = (u - self.cx) / self.fx;
            let my = (v - self.cy) / self.fy;
            [mx, my, (mx * mx + my * my).sqrt()]
        });
        let solve = m.map(|[_, _, r_d]| r_d.is_finite() && r_d != 0.0);
        let thetas = self.solve_thetas(m.map(|v| v[2]), solve);
        std::array::from_fn(|l| {
            let [mx, my, r_d] = m[l];
            if r_d == 0.0 {
                return Some([0.0, 0.0, 1.0]);
            }
            thetas[l].map(|(theta, _)| {
                let (s, c) = theta.sin_cos();
                [s * mx / r_d, s * my / r_d, c]
            })
        })
    }

    /// [`CameraModel::project`] without branches: `(u, v, ok)`, `u, v` unspecified where `ok`
    /// is false (a zero or non-finite ray, `theta > theta_max`, the ray straight back).
    #[inline(always)]
    fn project_branch_free(&self, x: f64, y: f64, z: f64) -> (f64, f64, bool) {
        // sqrt, not hypot: the ray is finite and O(1), so x^2 + y^2 cannot overflow, and hypot's
        // overflow care costs a fifth of the calibrated-offset computation.
        let rho = (x * x + y * y).sqrt();
        let theta = atan2_upper(rho, z);
        let r_d = self.distort(theta);
        let finite = x.is_finite() && y.is_finite() && z.is_finite();
        // On the axis: forward is the principal point; zero or backward has no single pixel.
        let on_axis = rho == 0.0;
        let ok = finite & if on_axis { z > 0.0 } else { theta <= self.theta_max };
        let u = if on_axis { self.cx } else { self.fx * r_d * (x / rho) + self.cx };
        let v = if on_axis { self.cy } else { self.fy * r_d * (y / rho) + self.cy };
        (u, v, ok)
    }

    #[inline(always)]
    fn project_columns_portable(
        &self,
        [x, y, z]: [&[f64]; 3],
        u: &mut [f64],
        v: &mut [f64],
        ok: &mut [bool],
    ) {
        let n = u.len();
        let (x, y, z, v, ok) = (&x[..n], &y[..n], &z[..n], &mut v[..n], &mut ok[..n]);
        for i in 0..n {
            (u[i], v[i], ok[i]) = self.project_branch_free(x[i], y[i], z[i]);
        }
    }

    /// [`KannalaBrandt::project_columns_portable`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn project_columns_avx2(
        &self,
        rays: [&[f64]; 3],
        u: &mut [f64],
        v: &mut [f64],
        ok: &mut [bool],
    ) {
        self.project_columns_portable(rays, u, v, ok);
    }
}

/// `tan(pi / 12) = 2 - sqrt(3)`: above it [`atan2_upper`] reduces its argument by `pi / 6`.
const TAN_PI_12: f64 = 0.267_949_192_431_122_7;
const SQRT_3: f64 = 1.732_050_807_568_877_2;

/// `atan2(y, x)` for `y >= 0` (the angle of a ray to the optical axis, in `[0, pi]`), without
/// branches or calls, so that loops over it vectorise: within 4.5e-16 rad of libm's `atan2`
/// (a test sweeps the half plane), NaN where either input is NaN or both are zero.
///
/// With `t = min(y, |x|) / max(y, |x|)` in `[0, 1]`: `atan(t) = pi/6 + atan(r)` with
/// `r = (sqrt(3) t - 1) / (t + sqrt(3))` for `t > tan(pi/12)` (else `r = t`), so `|r| <= tan(pi/12)`
/// and the Taylor series `atan(r) = r sum_n (-1)^n r^(2n) / (2n + 1)` truncated after 14 terms
/// is exact to `r^28 / 29 < 4e-18` relative; then `pi/2 - a` where `y > |x|` and `pi - a`
/// where `x < 0`.
#[inline(always)]
fn atan2_upper(y: f64, x: f64) -> f64 {
    use std::f64::consts::{FRAC_PI_2, FRAC_PI_6};
    let ax = x.abs();
    let steep = y > ax;
    let (lo, hi) = if steep { (ax, y) } else { (y, ax) };
    let t = lo / hi;
    let reduced = t > TAN_PI_12;
    let r = if reduced { (t * SQRT_3 - 1.0) / (t + SQRT_3) } else { t };
    let z = r * r;
    // sum_{n=0}^{13} (-1)^n z^n / (2n + 1), Horner from the smallest term.
    let mut p = -1.0 / 27.0;
    for n in (0..13).rev() {
        let c = 1.0 / (2 * n + 1) as f64;
        p = if n % 2 == 0 { c } else { -c } + z * p;
    }
    let a = r * p + if reduced { FRAC_PI_6 } else { 0.0 };
    let a = if steep { FRAC_PI_2 - a } else { a };
    if x < 0.0 {
        PI - a
    } else {
        a
    }
}

impl CameraModel for KannalaBrandt {
    /// `[fx d(theta) cos(phi) + cx, fy d(theta) sin(phi) + cy]` (module docs), or `None` for a
    /// zero or non-finite ray, for `theta > theta_max`, and for the ray pointing straight back
    /// (`theta = pi`, whose image is a circle, not a point).
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        let [x, y, z] = ray;
        let (u, v, ok) = self.project_branch_free(x, y, z);
        ok.then_some([u, v])
    }

    /// The rays of whole columns in a loop the compiler vectorises (no branches, no calls): with
    /// AVX2 where the CPU has it, 4 rays at a time. Same bits as [`CameraModel::project`] (the
    /// same expression, no fused multiply-adds).
    fn project_columns(&self, rays: [&[f64]; 3], u: &mut [f64], v: &mut [f64], ok: &mut [bool]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2, the only feature the function enables.
            return unsafe { self.project_columns_avx2(rays, u, v, ok) };
        }
        self.project_columns_portable(rays, u, v, ok);
    }

    /// With `r_d = sqrt(((u - cx) / fx)^2 + ((v - cy) / fy)^2)`, solves `d(theta) = r_d` (at most
    /// `solve::MAX_ITER` Newton steps, to the step tolerance `EPS`) and returns
    /// `[sin(theta) cos(phi), sin(theta) sin(phi), cos(theta)]`; `[0, 0, 1]` at the principal
    /// point. `None` for non-finite input, for `r_d > d(theta_max)` and if Newton does not
    /// converge.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let [ray] = self.unproject_lanes([px]);
        ray
    }

    /// Four pixels at a time through `KannalaBrandt::unproject_lanes` (their Newton
    /// iterations in lockstep), the last few one by one; each pixel gets the bits it gets alone.
    fn unproject_columns(&self, [pu, pv]: [&[f64]; 2], rays: [&mut [f64]; 3], ok: &mut [bool]) {
        const LANES: usize = 4;
        let [rx, ry, rz] = rays;
        let mut put = |i: usize, ray: Option<[f64; 3]>| {
            ok[i] = ray.is_some();
            [rx[i], ry[i], rz[i]] = ray.unwrap_or([0.0; 3]);
        };
        let n = pu.len().min(pv.len());
        let whole = n / LANES * LANES;
        for start in (0..whole).step_by(LANES) {
            let px = std::array::from_fn(|l| [pu[start + l], pv[start + l]]);
            for (l, ray) in self.unproject_lanes::<LANES>(px).into_iter().enumerate() {
                put(start + l, ray);
            }
        }
        for i in whole..n {
            put(i, self.unproject([pu[i], pv[i]]));
        }
    }

    fn size(&self) -> [usize; 2] {
        self.intrinsics.size()
    }

    /// `fov_deg` in radians.
    fn fov(&self) -> f64 {
        self.fov_deg.to_radians()
    }

    /// The intrinsics rescaled ([`Intrinsics::rescaled`]); `k` and `fov_deg` unchanged (they
    /// are angular).
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        let intrinsics = self.intrinsics.rescaled(scale, convention);
        Camera::KannalaBrandt(KannalaBrandt::unchecked(intrinsics, self.k, self.fov_deg))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::solve::MAX_ITER;
    use crate::camera::tests::{
        angle, assert_matches_central_differences, assert_newton_on_every_pixel, f195, kb,
    };

    /// Round trips are exact up to a few ulps of theta times fx (~1e-13 px); 1e-9 px leaves
    /// margin for sin/cos/atan2 rounding without hiding a real error (the Newton EPS is 1e-12 rad).
    const PX_TOL: f64 = 1e-9;
    /// Same in angle: 1e-9 rad is far above round-off (~1e-15) and far below anything visible.
    const ANGLE_TOL: f64 = 1e-9;
    /// Central differences with step 1e-6 on a unit-scale ray: truncation ~h^2 * f''' ~ 1e-10,
    /// cancellation ~eps * |u| / h ~ 1e-7 px; compared relative to the Jacobian's scale.
    const JAC_REL_TOL: f64 = 1e-6;
    /// Residual of `d(theta) = r_d` after Newton: quadratic convergence leaves round-off only.
    const RESIDUAL_TOL: f64 = 1e-12;
    /// Next to the fold the inverse is ill-conditioned: the angle error is ~1e-16 / d'(theta), and
    /// d' >= 2e-6 on the grid of the test below (measured worst: 8e-11 rad).
    const NEAR_FOLD_ANGLE_TOL: f64 = 1e-9;

    /// A made-up lens whose polynomial turns back: d' = 1 - 1.5 theta^2 = 0 at theta = sqrt(2/3).
    fn folding() -> KannalaBrandt {
        kb(
            300.0,
            300.0,
            500.0,
            400.0,
            [-0.5, 0.0, 0.0, 0.0],
            1000,
            800,
            90.0,
        )
    }

    #[test]
    fn atan2_upper_is_libm_atan2_to_a_few_ulps() {
        // The upper half plane at every angle step of 1e-5 rad, at radii from 1e-8 to 1e8, plus
        // points near the reduction's seams (tan(pi/12), 1) and the axes.
        let mut worst: f64 = 0.0;
        let mut check = |y: f64, x: f64| {
            let (got, want) = (atan2_upper(y, x), y.atan2(x));
            worst = worst.max((got - want).abs());
            assert!((got - want).abs() <= 4.5e-16, "atan2({y}, {x}): {got} vs {want}");
        };
        let steps = 314_160;
        for i in 0..=steps {
            let a = PI * i as f64 / steps as f64;
            for r in [1e-8, 0.3, 1.0, 7.0, 1e8] {
                check(r * a.sin(), r * a.cos());
            }
        }
        for t in [TAN_PI_12, 1.0] {
            let mut v = t;
            for _ in 0..50 {
                for x in [1.0, -1.0] {
                    check(v, x);
                    check(x.abs(), v * x);
                }
                v = v.next_up();
            }
        }
        assert_eq!(atan2_upper(0.0, 2.0), 0.0);
        assert_eq!(atan2_upper(0.0, -2.0), PI);
        assert_eq!(atan2_upper(2.0, 0.0), std::f64::consts::FRAC_PI_2);
        assert!(atan2_upper(0.0, 0.0).is_nan() && atan2_upper(f64::NAN, 1.0).is_nan());
        assert!(worst > 0.0, "the sweep should meet some rounding difference");
    }

    /// A way of filling `u, v, ok` from the test's ray columns.
    type ProjectInto<'a> = dyn Fn(&mut [f64], &mut [f64], &mut [bool]) + 'a;

    #[test]
    fn projecting_columns_gives_the_bits_of_project() {
        // Rays all around the sphere (past the fold of the folding lens), on the axis both ways,
        // zero and non-finite; with AVX2 and without.
        let mut rays: Vec<[f64; 3]> = Vec::new();
        for i in 0..=180 {
            let theta = PI * i as f64 / 180.0;
            for j in 0..37 {
                let phi = 2.0 * PI * j as f64 / 37.0;
                let r = 0.5 + j as f64 / 10.0;
                let (s, c) = theta.sin_cos();
                rays.push([r * s * phi.cos(), r * s * phi.sin(), r * c]);
            }
        }
        rays.extend([
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.0, 0.0, 0.0],
            [f64::NAN, 0.0, 1.0],
            [0.0, f64::INFINITY, 1.0],
            [0.1, 0.2, f64::NEG_INFINITY],
        ]);
        let cols: [Vec<f64>; 3] = [0, 1, 2].map(|c| rays.iter().map(|r| r[c]).collect());
        let cols = [&cols[0][..], &cols[1][..], &cols[2][..]];
        for cam in [f195(), folding()] {
            let n = rays.len();
            let run = |f: &ProjectInto| {
                let (mut u, mut v, mut ok) = (vec![0.0; n], vec![0.0; n], vec![false; n]);
                f(&mut u, &mut v, &mut ok);
                (u, v, ok)
            };
            let dispatched = run(&|u, v, ok| cam.project_columns(cols, u, v, ok));
            let portable = run(&|u, v, ok| cam.project_columns_portable(cols, u, v, ok));
            let mut lanes = vec![portable];
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2.
                lanes.push(run(&|u, v, ok| unsafe { cam.project_columns_avx2(cols, u, v, ok) }));
            }
            lanes.push(dispatched);
            let mut failed = 0;
            for (i, ray) in rays.iter().enumerate() {
                let want = cam.project(*ray);
                failed += usize::from(want.is_none());
                for (u, v, ok) in &lanes {
                    let got = ok[i].then(|| [u[i], v[i]]);
                    let bits = |p: Option<[f64; 2]>| p.map(|p| p.map(f64::to_bits));
                    assert_eq!(bits(got), bits(want), "ray {ray:?}");
                }
            }
            assert!(failed >= 5, "the specials and the folded rays must not project: {failed}");
        }
    }

    #[test]
    fn theta_max_is_pi_for_f195_and_the_fold_for_a_folding_polynomial() {
        assert_eq!(f195().theta_max(), PI);
        let t = folding().theta_max();
        assert!((t - (2.0f64 / 3.0).sqrt()).abs() < 1e-12, "{t}");
        assert!(folding().is_monotonic_to(0.8));
        assert!(!folding().is_monotonic_to(0.9));
    }

    #[test]
    fn principal_point_is_the_optical_axis() {
        let cam = f195();
        assert_eq!(cam.unproject([540.0, 480.0]), Some([0.0, 0.0, 1.0]));
        assert_eq!(cam.project([0.0, 0.0, 2.5]), Some([540.0, 480.0]));
    }

    #[test]
    fn rays_past_90_degrees_project_and_come_back() {
        let cam = f195();
        for deg in [90.0f64, 95.0, 97.5, 120.0, 170.0] {
            let t = deg.to_radians();
            let ray = [t.sin() * 0.6, t.sin() * 0.8, t.cos()];
            let px = cam.project(ray).expect("past 90 deg projects");
            let back = cam.unproject(px).unwrap();
            assert!(angle(ray, back) < ANGLE_TOL, "{deg}: {ray:?} -> {back:?}");
            let again = cam.project(back).unwrap();
            assert!((again[0] - px[0]).hypot(again[1] - px[1]) < PX_TOL, "{deg}");
        }
        // The edge of the 195 degree circle lies inside the image width (r ~ 488 px < 540).
        let t = 97.5f64.to_radians();
        let [u, _] = cam.project([t.sin(), 0.0, t.cos()]).unwrap();
        assert!(u > 1000.0 && u < 1079.5, "{u}");
    }

    #[test]
    fn outside_the_domain_is_none() {
        let cam = folding();
        let tm = cam.theta_max();
        let inside = tm - 1e-6;
        let outside = tm + 1e-3;
        assert!(cam.project([inside.sin(), 0.0, inside.cos()]).is_some());
        assert_eq!(cam.project([outside.sin(), 0.0, outside.cos()]), None);
        let edge = cam.fx * cam.distort(tm);
        assert!(cam.unproject([cam.cx + edge * 0.999, cam.cy]).is_some());
        assert_eq!(cam.unproject([cam.cx + edge * 1.001, cam.cy]), None);
        // Beyond d(pi) for F195.
        let f = f195();
        let edge = f.fx * f.distort(PI);
        assert_eq!(f.unproject([f.cx, f.cy + edge + 1.0]), None);
        // Degenerate rays and pixels.
        assert_eq!(f.project([0.0, 0.0, 0.0]), None);
        assert_eq!(f.project([0.0, 0.0, -1.0]), None);
        assert_eq!(f.project([f64::NAN, 0.0, 1.0]), None);
        assert_eq!(f.project([f64::INFINITY, 0.0, 1.0]), None);
        assert_eq!(f.unproject([f64::NAN, 0.0]), None);
    }

    #[test]
    fn round_trips_on_the_folding_lens_up_to_theta_max() {
        let cam = folding();
        let tm = cam.theta_max();
        for i in 0..=200 {
            let t = tm * i as f64 / 200.0 * 0.999_999;
            for phi in [0.3f64, 2.0, 4.0] {
                let ray = [t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()];
                let back = cam.unproject(cam.project(ray).unwrap()).unwrap();
                let err = angle(ray, back);
                assert!(err < NEAR_FOLD_ANGLE_TOL, "theta {t}: {err}");
            }
        }
    }

    #[test]
    fn newton_converges_on_every_f195_pixel() {
        let cam = f195();
        // Newton starts from theta = r_d.
        let solve = |[mx, my]: [f64; 2]| {
            let r_d = mx.hypot(my);
            let (theta, iters) = cam.solve_theta(r_d).expect("converges");
            (iters, (cam.distort(theta) - r_d).abs())
        };
        let worst = assert_newton_on_every_pixel(&cam, solve, [4, 3], RESIDUAL_TOL);
        assert!(worst < MAX_ITER, "{worst}");
    }

    #[test]
    fn newton_converges_next_to_a_double_root() {
        // At theta_max d' = 0: Newton is only linear there, the bracket keeps it safe.
        let cam = folding();
        let r_max = cam.distort(cam.theta_max());
        for r_d in [r_max, r_max * (1.0 - 1e-12), r_max * (1.0 - 1e-6)] {
            let (theta, iters) = cam.solve_theta(r_d).expect("converges");
            assert!(iters < MAX_ITER);
            assert!((cam.distort(theta) - r_d).abs() < RESIDUAL_TOL);
        }
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let cam = f195();
        let h = 1e-6;
        for deg in [0.0f64, 0.5, 10.0, 45.0, 89.0, 90.0, 120.0, 160.0] {
            for phi in [0.0f64, 0.7, 2.5, 4.0] {
                for len in [0.5, 1.0, 2.0] {
                    let t = deg.to_radians();
                    let ray = [
                        len * t.sin() * phi.cos(),
                        len * t.sin() * phi.sin(),
                        len * t.cos(),
                    ];
                    let jac = cam.project_jacobian(ray).unwrap();
                    let scale = cam.fx / len;
                    assert_matches_central_differences(
                        |r| cam.project(r).unwrap(),
                        ray,
                        h,
                        &jac,
                        JAC_REL_TOL * scale,
                        &format!("theta {deg} phi {phi} len {len}"),
                    );
                }
            }
        }
    }

    #[test]
    fn rescaled_by_both_conventions() {
        let cam = f195();
        let Camera::KannalaBrandt(half) = cam.rescaled([0.5, 0.25], PixelConvention::HalfPixel)
        else {
            panic!("model changed");
        };
        // fx 287 * 0.5, fy 287 * 0.25, cx (540.5) * 0.5 - 0.5, cy (480.5) * 0.25 - 0.5.
        assert_eq!(
            half,
            kb(143.5, 71.75, 269.75, 119.625, cam.k, 540, 240, 195.0)
        );
        let Camera::KannalaBrandt(paper) = cam.rescaled([0.5, 0.25], PixelConvention::Paper) else {
            panic!("model changed");
        };
        assert_eq!(
            paper,
            kb(143.5, 71.75, 270.0, 120.0, cam.k, 540, 240, 195.0)
        );
        assert_eq!(half.theta_max(), cam.theta_max());
        assert_eq!(half.fov(), 195.0f64.to_radians());
        assert_eq!(half.size(), [540, 240]);
    }
}
