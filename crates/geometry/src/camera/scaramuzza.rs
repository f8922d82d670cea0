//! Scaramuzza's omnidirectional model, as calibrated by the OCamCalib toolbox (Scaramuzza,
//! Martinelli and Siegwart, "A Toolbox for Easily Calibrating Omnidirectional Cameras", IROS
//! 2006; the conventions are those of the toolbox's `ocam_functions.c`, `cam2world` and
//! `world2cam`, and of its exported `calib_results.txt`).
//!
//! OCamCalib's own frame: its image "x" is the **row** and "y" the **column**; the sensor-plane
//! point `(xp, yp)` maps to the 3-D direction `(xp, yp, f(rho))` with
//! `f(rho) = a0 + a1 rho + a2 rho^2 + ...` (`a0 < 0`: the camera looks along OCamCalib's `-z`),
//! and pixels are `[row, col] = A [xp, yp] + [xc, yc]` with the affine `A = [[c, d], [e, 1]]`
//! (zero-based centre, "C convention"). In this crate's frame (x right, y down, z forward; pixels `[u, v]` =
//! (column, row)) that reads, with `cx = yc` (column) and `cy = xc` (row):
//!
//! ```text
//! unproject: X' = (c (u - cx) - e (v - cy)) / (c - d e)      (= OCamCalib's yp)
//!            Y' = ((v - cy) - d (u - cx)) / (c - d e)        (= OCamCalib's xp)
//!            rho = sqrt(X'^2 + Y'^2),  ray = [X', Y', -f(rho)] / |...|
//! project:   theta = atan2(sqrt(x^2 + y^2), z)  (angle to the optical axis)
//!            rho solves  rho cos(theta) + f(rho) sin(theta) = 0   (the direction of
//!            [rho, -f(rho)] is theta),  w = rho / sqrt(x^2 + y^2)
//!            u = w (x + e y) + cx,   v = w (d x + c y) + cy
//! ```
//!
//! `project` solves the direct polynomial exactly (the shared safeguarded Newton, `MAX_ITER`,
//! `EPS`, with its residual checked against `RESIDUAL_TOL`), so pixels round-trip; OCamCalib's
//! `world2cam` instead evaluates its fitted inverse polynomial `rho = b0 + b1 t + b2 t^2 + ...`
//! of `t = atan(-z / sqrt(x^2 + y^2)) = theta - pi/2`, which differs from the exact inverse by
//! its fit error: 0.003 to 0.29 px at worst over the image, measured on six OCamCalib
//! calibrations. Here that inverse polynomial (`inv_poly`, optional) only seeds Newton.
//!
//! The model is valid where the angle to the axis, `g(rho) = atan2(rho, -f(rho))`, increases:
//! `rho f'(rho) - f(rho) > 0`, from `rho = 0` up to the first fold `rho_max` (searched up to twice
//! the image diagonal). Rays beyond `theta_max = g(rho_max)` and pixels beyond `rho_max` are
//! `None`. Angles in radians.

use std::f64::consts::{FRAC_PI_2, PI};

use super::schema::{
    check_finite, check_fov, check_fov_in_domain, check_size, checked, float_list, raw_camera_file,
    write_fields, CameraFile, Checked, Invalid,
};
use super::intrinsics::eq_by_fields;
use super::solve::{increasing_root, last_ok};
use super::{Camera, CameraModel, PixelConvention};
use crate::vec3::{normalize, project_off_axis};

/// Convergence threshold on the Newton step, in pixels of `rho`: far below anything visible,
/// far above the ~1e-13 px round-off of `rho ~ 1e3`, so the test can fire.
pub const EPS: f64 = 1e-10;

/// The largest residual `|g(rho) - theta|` (radians) a projected radius may leave: at the
/// ~1e3 px per radian of a fisheye it is ~1e-7 px, below the 1e-6 px the imports are checked
/// to; a converged Newton leaves ~1e-16.
pub const RESIDUAL_TOL: f64 = 1e-10;

/// Grid points scanning `rho f'(rho) - f(rho)` for its first non-positive value.
const SCAN_STEPS: usize = 20_000;

/// Longest polynomial accepted (OCamCalib's `MAX_POL_LENGTH` is 64).
const MAX_POLY_LEN: usize = 64;

/// A camera of Scaramuzza's model (OCamCalib).
///
/// Build it with [`Scaramuzza::new`], which finds the valid range `rho_max`. Equality compares
/// the public fields only.
#[derive(Clone, Debug)]
pub struct Scaramuzza {
    /// Direct polynomial `f(rho) = a0 + a1 rho + ...`, ascending powers (OCamCalib's `ss`, the
    /// first block of `calib_results.txt`); `a0 < 0`.
    pub poly: Vec<f64>,
    /// Inverse polynomial `rho(t)`, ascending powers of `t = theta - pi/2` (OCamCalib's
    /// `invpol`); only a starting guess here, may be empty.
    pub inv_poly: Vec<f64>,
    /// Centre column, pixels (OCamCalib's `yc`, zero-based).
    pub cx: f64,
    /// Centre row, pixels (OCamCalib's `xc`, zero-based).
    pub cy: f64,
    /// Affine parameter `c` (OCamCalib's order: it multiplies the row component).
    pub c: f64,
    /// Affine parameter `d`.
    pub d: f64,
    /// Affine parameter `e`.
    pub e: f64,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Full field of view of the lens, in degrees (not in `calib_results.txt`: see the importer).
    pub fov_deg: f64,
    rho_max: f64,
}

eq_by_fields!(Scaramuzza: poly, inv_poly, cx, cy, c, d, e, width, height, fov_deg);

raw_camera_file! {
    /// A Scaramuzza (OCamCalib) camera file as written. `cx` is the centre column (OCamCalib's
    /// `yc`), `cy` the centre row (its `xc`).
    struct Raw {
        width: usize,
        height: usize,
        fov_deg: f64,
        cx: f64,
        cy: f64,
        c: f64,
        d: f64,
        e: f64,
        poly: Vec<f64>,
        #[serde(default)]
        inv_poly: Vec<f64>,
    }
}

impl CameraFile for Scaramuzza {
    const MODEL: &'static str = "scaramuzza";
    type Raw = Raw;
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        let (cde, size) = ([r.c, r.d, r.e], [r.width, r.height]);
        Scaramuzza::new(r.poly, r.inv_poly, [r.cx, r.cy], cde, size, r.fov_deg)
    }
    fn fields(&self) -> Vec<(&'static str, f64)> {
        let fields = [("fov_deg", self.fov_deg), ("cx", self.cx), ("cy", self.cy)];
        let mut fields = fields.to_vec();
        fields.extend([("c", self.c), ("d", self.d), ("e", self.e)]);
        fields
    }
    /// The float fields, then `poly` and (when given) `inv_poly`.
    fn write_fields(&self, out: &mut String) {
        write_fields(out, self.size(), &self.fields());
        out.push_str(&format!("poly = {}\n", float_list(&self.poly)));
        if !self.inv_poly.is_empty() {
            out.push_str(&format!("inv_poly = {}\n", float_list(&self.inv_poly)));
        }
    }
}

impl Scaramuzza {
    /// A checked camera (see [`Scaramuzza::validate`]) with these parameters (see the field
    /// docs; `centre = [cx, cy]`, `size = [width, height]`); computes `rho_max`.
    pub fn new(
        poly: Vec<f64>,
        inv_poly: Vec<f64>,
        centre: [f64; 2],
        cde: [f64; 3],
        size: [usize; 2],
        fov_deg: f64,
    ) -> Result<Self, Invalid> {
        checked(
            Self::unchecked(poly, inv_poly, centre, cde, size, fov_deg),
            Self::validate,
        )
    }

    /// The camera without the checks (for rescaling a checked camera and probing the domain).
    pub(crate) fn unchecked(
        poly: Vec<f64>,
        inv_poly: Vec<f64>,
        [cx, cy]: [f64; 2],
        [c, d, e]: [f64; 3],
        [width, height]: [usize; 2],
        fov_deg: f64,
    ) -> Self {
        let mut cam = Scaramuzza {
            poly,
            inv_poly,
            cx,
            cy,
            c,
            d,
            e,
            width,
            height,
            fov_deg,
            rho_max: 0.0,
        };
        cam.rho_max = cam.find_rho_max();
        cam
    }

    /// Every float finite, at most `MAX_POLY_LEN` (64) coefficients, `a0 < 0`, `c - d e > 0`,
    /// `width, height > 0`, `0 < fov_deg < 360` and `fov_deg / 2` below
    /// [`Scaramuzza::theta_max`]; the error names the field.
    pub fn validate(&self) -> Checked {
        check_finite(self.fields())?;
        for (field, list) in [("poly", &self.poly), ("inv_poly", &self.inv_poly)] {
            if let Some((i, v)) = list.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                let message = format!("coefficient {i} must be finite, found {v}");
                return Err(Invalid::new(field, message));
            }
            if list.len() > MAX_POLY_LEN {
                let message = format!("{} coefficients, at most {MAX_POLY_LEN}", list.len());
                return Err(Invalid::new(field, message));
            }
        }
        match self.poly.first() {
            Some(&a0) if a0 < 0.0 => {}
            other => {
                return Err(Invalid::new(
                    "poly",
                    format!(
                        "the first coefficient a0 must be negative (OCamCalib's cameras look \
                         along -z), found {other:?}"
                    ),
                ))
            }
        }
        let det = self.c - self.d * self.e;
        if det.is_nan() || det <= 0.0 {
            return Err(Invalid::new(
                "c, d, e",
                format!("the affine matrix [[c, d], [e, 1]] must have c - d e > 0, found {det}"),
            ));
        }
        check_size(self.width, self.height)?;
        check_fov(self.fov_deg)?;
        check_fov_in_domain(self.fov_deg, self.theta_max(), "poly")
    }

    /// `f(rho) = sum a_i rho^i` (Horner).
    pub fn f(&self, rho: f64) -> f64 {
        self.poly.iter().rev().fold(0.0, |acc, a| acc * rho + a)
    }

    /// `f'(rho) = sum i a_i rho^(i-1)`.
    pub fn f_derivative(&self, rho: f64) -> f64 {
        self.poly
            .iter()
            .enumerate()
            .skip(1)
            .rev()
            .fold(0.0, |acc, (i, a)| acc * rho + i as f64 * a)
    }

    /// OCamCalib's inverse polynomial `rho(t) = sum b_i t^i`, `t = theta - pi/2` (its
    /// `world2cam`); `None` if the file gave none.
    pub fn inv_poly_rho(&self, theta: f64) -> Option<f64> {
        let t = theta - FRAC_PI_2;
        (!self.inv_poly.is_empty())
            .then(|| self.inv_poly.iter().rev().fold(0.0, |acc, b| acc * t + b))
    }

    /// Angle to the optical axis of sensor radius `rho`: `g(rho) = atan2(rho, -f(rho))`.
    pub fn angle_at(&self, rho: f64) -> f64 {
        rho.atan2(-self.f(rho))
    }

    /// End of the valid sensor radius (pixels before the affine map).
    pub fn rho_max(&self) -> f64 {
        self.rho_max
    }

    /// Largest angle to the optical axis that projects: `g(rho_max)`, radians.
    pub fn theta_max(&self) -> f64 {
        self.angle_at(self.rho_max)
    }

    /// Scans `rho f'(rho) - f(rho) > 0` on `[0, 2 * image diagonal]`, bisecting the first failure.
    fn find_rho_max(&self) -> f64 {
        let ok = |r: f64| r * self.f_derivative(r) - self.f(r) > 0.0 && self.angle_at(r) < PI;
        let limit = 2.0 * (self.width as f64).hypot(self.height as f64);
        if !ok(0.0) || limit.is_nan() || limit <= 0.0 {
            return 0.0;
        }
        let step = limit / SCAN_STEPS as f64;
        last_ok(ok, 0.0, (1..=SCAN_STEPS).map(|i| i as f64 * step)).unwrap_or(limit)
    }

    /// Solves `g(rho) = theta` on `[0, rho_max]`, where `g(rho) = atan2(rho, -f(rho))` increases
    /// (so the bracket is kept by the sign of `g - theta`), by Newton with
    /// `g'(rho) = (rho f'(rho) - f(rho)) / (rho^2 + f(rho)^2)` and a bisection step whenever
    /// Newton would leave the bracket (the shared [`increasing_root`]). Seeded by the inverse polynomial when it lands inside the
    /// bracket, else by the paraxial `rho = -a0 theta`. Converged when `|step| < EPS`. Returns
    /// `(rho, iterations)`, or `None` without convergence or for `theta` outside
    /// `[0, theta_max]`.
    pub(crate) fn solve_rho(&self, theta: f64) -> Option<(f64, usize)> {
        if !(theta >= 0.0 && theta <= self.theta_max()) {
            return None;
        }
        if theta == 0.0 {
            return Some((0.0, 0));
        }
        let inside = |r: f64| r > 0.0 && r < self.rho_max;
        let rho = match self.inv_poly_rho(theta) {
            Some(r) if inside(r) => r,
            _ => -self.poly[0] * theta,
        };
        let g = |rho: f64| {
            let f = self.f(rho);
            let slope = (rho * self.f_derivative(rho) - f) / (rho * rho + f * f);
            (rho.atan2(-f) - theta, slope)
        };
        increasing_root(g, [0.0, self.rho_max], rho, [EPS, RESIDUAL_TOL])
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None`. With `q = sqrt(x^2 + y^2)`, `w = rho / q` and `rho(q, z)` defined
    /// implicitly by `G = rho z + f(rho) q = 0`:
    ///
    /// ```text
    /// drho/dq = -f(rho) / (z + q f'(rho)),   drho/dz = -rho / (z + q f'(rho))
    /// dw/dx = x / q^2 (drho/dq - w),  dw/dy = y / q^2 (drho/dq - w),  dw/dz = drho/dz / q
    /// du/dp = w [1, e, 0] + (x + e y) dw/dp,   dv/dp = w [d, c, 0] + (d x + c y) dw/dp
    /// ```
    ///
    /// On the axis (`q = 0`) `w = -a0 / z` and the `dw` terms vanish.
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        let q = x.hypot(y);
        let (w, dw) = if q == 0.0 {
            (-self.poly[0] / z, [0.0; 3])
        } else {
            let rho = self.solve_rho(q.atan2(z))?.0;
            let w = rho / q;
            let den = z + q * self.f_derivative(rho);
            let (drho_dq, drho_dz) = (-self.f(rho) / den, -rho / den);
            (
                w,
                [
                    x / (q * q) * (drho_dq - w),
                    y / (q * q) * (drho_dq - w),
                    drho_dz / q,
                ],
            )
        };
        let (a, b) = (x + self.e * y, self.d * x + self.c * y);
        let (ru, rv) = ([1.0, self.e, 0.0], [self.d, self.c, 0.0]);
        Some([
            [0, 1, 2].map(|i| w * ru[i] + a * dw[i]),
            [0, 1, 2].map(|i| w * rv[i] + b * dw[i]),
        ])
    }
}

impl CameraModel for Scaramuzza {
    /// Module docs; `None` for a zero or non-finite ray, for `theta > theta_max`, and for the
    /// backward ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        project_off_axis(ray, [self.cx, self.cy], |[x, y, z], q| {
            let (rho, _) = self.solve_rho(q.atan2(z))?;
            let w = rho / q;
            Some([
                w * (x + self.e * y) + self.cx,
                w * (self.d * x + self.c * y) + self.cy,
            ])
        })
    }

    /// OCamCalib's `cam2world` in this crate's frame (module docs); `None` beyond `rho_max` and
    /// for non-finite pixels.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let (du, dv) = (px[0] - self.cx, px[1] - self.cy);
        let det = self.c - self.d * self.e;
        let xs = (self.c * du - self.e * dv) / det;
        let ys = (dv - self.d * du) / det;
        let rho = xs.hypot(ys);
        if rho.is_nan() || rho > self.rho_max {
            return None;
        }
        normalize([xs, ys, -self.f(rho)])
    }

    fn size(&self) -> [usize; 2] {
        [self.width, self.height]
    }

    /// `fov_deg` in radians.
    fn fov(&self) -> f64 {
        self.fov_deg.to_radians()
    }

    /// Sensor radii scale by `sx`: `a_i' = a_i sx^(1 - i)`, `b_i' = sx b_i`; rows by `sy`:
    /// `c' = c sy / sx`, `d' = d sy / sx`, `e' = e`; the centre moves by `convention`; size
    /// `round(width sx)` x `round(height sy)`.
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        let [sx, sy] = scale;
        let ratio = sy / sx;
        let poly = self
            .poly
            .iter()
            .enumerate()
            .map(|(i, a)| a * sx.powi(1 - i as i32))
            .collect();
        let inv_poly = self.inv_poly.iter().map(|b| b * sx).collect();
        Camera::Scaramuzza(Scaramuzza::unchecked(
            poly,
            inv_poly,
            [
                convention.scale_centre(self.cx, sx),
                convention.scale_centre(self.cy, sy),
            ],
            [self.c * ratio, self.d * ratio, self.e],
            [
                (self.width as f64 * sx).round() as usize,
                (self.height as f64 * sy).round() as usize,
            ],
            self.fov_deg,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera from positional parameters, unchecked.
    #[allow(clippy::too_many_arguments)]
    fn ocam(
        poly: Vec<f64>,
        inv_poly: Vec<f64>,
        cx: f64,
        cy: f64,
        cde: [f64; 3],
        width: usize,
        height: usize,
        fov_deg: f64,
    ) -> Scaramuzza {
        Scaramuzza::unchecked(poly, inv_poly, [cx, cy], cde, [width, height], fov_deg)
    }
    use crate::vec3::angle_to_axis;

    /// Newton to |step| < 1e-10 px with quadratic convergence: round-off only (~1e-13 px);
    /// 1e-9 px is margin.
    const PX_TOL: f64 = 1e-9;
    /// Angles after Newton on the angle itself: round-off of atan2 (~1e-16 rad); 1e-12 is margin.
    const ANGLE_TOL: f64 = 1e-12;
    /// The same formula evaluated in a different frame order: a few ulps of a unit vector.
    const SAME_FORMULA_TOL: f64 = 1e-15;
    /// The example's inverse polynomial was fitted to 0.041 px max error over rho <= 340 px
    /// (tools: numpy polyfit, degree 11): OCamCalib's world2cam may differ from the exact
    /// inverse by that much, and 0.05 px bounds it.
    const INV_POLY_FIT_PX: f64 = 0.05;

    /// `data/cameras/ocam_example.toml`.
    fn example() -> Scaramuzza {
        ocam(
            vec![-181.0, 0.0, 0.005213419, -2.499194e-05, 4.96439e-08],
            vec![
                290.61471853,
                184.70074695,
                -69.419725463,
                37.135138721,
                108.7624902,
                -334.10471638,
                -310.55283528,
                963.61075172,
                1973.5887201,
                1515.1133615,
                548.12413232,
                78.012098572,
            ],
            401.3,
            318.7,
            [1.0003, 0.0002, -0.0004],
            800,
            640,
            190.0,
        )
    }

    /// OCamCalib's `cam2world` from `ocam_functions.c`, transcribed in its own frame: `p` is
    /// `[row, col]`, the result is OCamCalib's `[x, y, z]` (x along rows, z backward).
    fn ocam_cam2world(m: &Scaramuzza, p: [f64; 2]) -> [f64; 3] {
        let (xc, yc) = (m.cy, m.cx);
        let invdet = 1.0 / (m.c - m.d * m.e);
        let xp = invdet * ((p[0] - xc) - m.d * (p[1] - yc));
        let yp = invdet * (-m.e * (p[0] - xc) + m.c * (p[1] - yc));
        let r = xp.hypot(yp);
        let mut zp = m.poly[0];
        let mut r_i = 1.0;
        for a in &m.poly[1..] {
            r_i *= r;
            zp += r_i * a;
        }
        let invnorm = 1.0 / (xp * xp + yp * yp + zp * zp).sqrt();
        [invnorm * xp, invnorm * yp, invnorm * zp]
    }

    /// OCamCalib's `world2cam` from `ocam_functions.c`, transcribed: OCamCalib frame in,
    /// `[row, col]` out.
    fn ocam_world2cam(m: &Scaramuzza, p: [f64; 3]) -> [f64; 2] {
        let (xc, yc) = (m.cy, m.cx);
        let norm = p[0].hypot(p[1]);
        if norm == 0.0 {
            return [xc, yc];
        }
        let theta = (p[2] / norm).atan();
        let mut rho = m.inv_poly[0];
        let mut t_i = 1.0;
        for b in &m.inv_poly[1..] {
            t_i *= theta;
            rho += t_i * b;
        }
        let (x, y) = (p[0] / norm * rho, p[1] / norm * rho);
        [x * m.c + y * m.d + xc, x * m.e + y + yc]
    }

    #[test]
    fn unproject_is_ocamcalib_cam2world_with_axes_swapped() {
        let m = example();
        for (u, v) in [
            (401.3, 318.7),
            (0.0, 0.0),
            (120.5, 600.0),
            (700.0, 50.25),
            (500.0, 330.0),
        ] {
            let ours = m.unproject([u, v]).unwrap();
            let [xo, yo, zo] = ocam_cam2world(&m, [v, u]);
            // OCamCalib x = our y (rows), y = our x (columns), z = -our z.
            let err = (ours[0] - yo).abs() + (ours[1] - xo).abs() + (ours[2] + zo).abs();
            assert!(
                err < SAME_FORMULA_TOL,
                "({u}, {v}): {ours:?} vs {:?}",
                [xo, yo, zo]
            );
        }
    }

    #[test]
    fn project_matches_ocamcalib_world2cam_within_the_inverse_fit() {
        let m = example();
        let mut worst = 0.0f64;
        // theta up to 95 deg (the 190 deg field of view), the range the inverse was fitted on.
        for i in 0..=95 {
            let t = (i as f64).to_radians();
            for phi in [0.0f64, 0.8, 2.0, 3.5, 5.0] {
                let ray = [t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos()];
                let ours = m.project(ray).unwrap();
                let [row, col] = ocam_world2cam(&m, [ray[1], ray[0], -ray[2]]);
                worst = worst.max((ours[0] - col).hypot(ours[1] - row));
            }
        }
        assert!(worst < INV_POLY_FIT_PX, "{worst} px");
        // And the comparison can fail: it sees a change of the affine part.
        let mut off = example();
        off.e = 0.01;
        let ray = [0.5, 0.5, 0.5];
        let ours = off.project(ray).unwrap();
        let [row, col] = ocam_world2cam(&example(), [ray[1], ray[0], -ray[2]]);
        assert!((ours[0] - col).hypot(ours[1] - row) > 1.0);
    }

    #[test]
    fn newton_converges_and_round_trips() {
        let m = example();
        let (mut worst, mut worst_in_fov) = (0, 0);
        for i in 0..=400 {
            let t = m.theta_max() * i as f64 / 400.0 * 0.999_999;
            let (rho, iters) = m.solve_rho(t).expect("converges");
            worst = worst.max(iters);
            if t <= m.fov() / 2.0 {
                worst_in_fov = worst_in_fov.max(iters);
            }
            assert!((m.angle_at(rho) - t).abs() < ANGLE_TOL, "{t}");
            let ray = [t.sin(), 0.0, t.cos()];
            let px = m.project(ray).unwrap();
            let back = m.unproject(px).unwrap();
            assert!((angle_to_axis(back) - t).abs() < ANGLE_TOL);
            let again = m.project(back).unwrap();
            assert!((again[0] - px[0]).hypot(again[1] - px[1]) < PX_TOL);
        }
        // Measured: 3 inside the 190 deg field of view, 11 next to theta_max = 179.8 deg, where
        // g is nearly flat over thousands of pixels of rho.
        assert!(
            worst_in_fov <= 4,
            "{worst_in_fov} iterations inside the field of view"
        );
        assert!(worst <= 12, "{worst} iterations");
    }

    #[test]
    fn domain_ends_at_the_fold() {
        // f(rho) = -100 + 0.01 rho^2 - 1e-5 rho^3: rho f' - f = 100 + 0.01 rho^2 - 2e-5 rho^3,
        // positive up to its root near 518.6 px.
        let m = ocam(
            vec![-100.0, 0.0, 0.01, -1e-5],
            vec![],
            500.0,
            500.0,
            [1.0, 0.0, 0.0],
            1000,
            1000,
            180.0,
        );
        let h = |r: f64| 100.0 + 0.01 * r * r - 2e-5 * r * r * r;
        assert!(
            h(m.rho_max() - 1e-6) > 0.0 && h(m.rho_max() + 1e-3) < 0.0,
            "{}",
            m.rho_max()
        );
        assert!(m.unproject([500.0 + m.rho_max() * 0.999, 500.0]).is_some());
        assert_eq!(m.unproject([500.0 + m.rho_max() * 1.001, 500.0]), None);
        let tm = m.theta_max();
        assert!(m
            .project([(tm - 1e-6).sin(), 0.0, (tm - 1e-6).cos()])
            .is_some());
        assert_eq!(m.project([(tm + 1e-3).sin(), 0.0, (tm + 1e-3).cos()]), None);
    }
}
