//! The Extended Unified Camera Model (EUCM) of Khomutenko, Garcia and Martinet, "An Enhanced
//! Unified Camera Model", IEEE RA-L 2016, in the form of Usenko et al., "The Double Sphere Camera
//! Model", 3DV 2018 (Section 3.4, Eqs. 22-29; Basalt's and Kalibr's `eucm`). The unit sphere of
//! the unified model becomes an ellipsoid of parameter `beta`.
//!
//! Projection of a ray `[x, y, z]` (camera frame: x right, y down, z forward), Eqs. 22-24:
//!
//! ```text
//! d = sqrt(beta (x^2 + y^2) + z^2)
//! u = fx x / (alpha d + (1 - alpha) z) + cx
//! v = fy y / (alpha d + (1 - alpha) z) + cy
//! ```
//!
//! defined where `z > -w d` (Eq. 25) with `w = alpha / (1 - alpha)` for `alpha <= 0.5`, else
//! `(1 - alpha) / alpha`. On the boundary `z^2 (1 - w^2) = w^2 beta (x^2 + y^2)`, so the angle
//! to the optical axis is below `theta_max = pi - atan2(sqrt(1 - w^2), w sqrt(beta))`.
//! `beta = 1` is the unified model ([`super::Unified`]).
//!
//! Unprojection, Eqs. 26-29 (closed form):
//!
//! ```text
//! mx = (u - cx) / fx,  my = (v - cy) / fy,  r^2 = mx^2 + my^2
//! mz = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)
//! ray = [mx, my, mz] / |[mx, my, mz]|
//! ```
//!
//! defined for `r^2 <= 1 / (beta (2 alpha - 1))` when `alpha > 0.5`. Parameters: `alpha in
//! [0, 1]`, `beta > 0` (checked by the camera file reader). Pixels are `[u, v]` = (column, row),
//! top-left pixel centre at `(0, 0)`; radians.

use super::intrinsics::{fisheye_extent, Divided};
use super::schema::{
    check_rule, check_unit_interval, plain_fisheye_file, CameraFile, Checked,
};
use super::unified::{unified_den, unified_w};
use super::{CameraModel, Intrinsics};
use crate::vec3::normalize;

/// The unnormalised ray `m = [mx, my, mz]` of pixel `px` and its `r^2 = mx^2 + my^2` (Eqs.
/// 26-29): `mx = (u - cx) / fx`, `my = (v - cy) / fy`,
/// `mz = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)`; `None`
/// where the square root is imaginary (or NaN). With `beta = 1` it is the double sphere's first
/// step (Usenko et al. 2018, Eqs. 44-47), bit for bit (`1 x = x`).
pub(super) fn eucm_m(
    k: &Intrinsics,
    alpha: f64,
    beta: f64,
    px: [f64; 2],
) -> Option<([f64; 3], f64)> {
    let mx = (px[0] - k.cx) / k.fx;
    let my = (px[1] - k.cy) / k.fy;
    let r2 = mx * mx + my * my;
    let disc = 1.0 - (2.0 * alpha - 1.0) * beta * r2;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let mz = (1.0 - beta * alpha * alpha * r2) / (alpha * disc.sqrt() + 1.0 - alpha);
    Some(([mx, my, mz], r2))
}

/// An Extended Unified Camera Model camera. Plain parameters, nothing cached.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtendedUnified {
    intrinsics: Intrinsics,
    /// Projection parameter in `[0, 1]`.
    pub alpha: f64,
    /// Ellipsoid parameter, `> 0` (1: the unit sphere of the unified model).
    pub beta: f64,
    /// Full field of view of the lens, in degrees (as declared by the calibration).
    pub fov_deg: f64,
}

plain_fisheye_file!(ExtendedUnified, "extended-unified", [alpha, beta]);

impl ExtendedUnified {
    /// `alpha in [0, 1]` and `beta > 0` (part of [`ExtendedUnified::validate`]).
    fn check_parameters(&self) -> Checked {
        check_unit_interval("alpha", self.alpha)?;
        check_rule("beta", self.beta, self.beta > 0.0, "> 0")
    }

    /// Largest angle to the optical axis that projects, in radians (exclusive):
    /// `pi - atan2(sqrt(1 - w^2), w sqrt(beta))`.
    pub fn theta_max(&self) -> f64 {
        let w = unified_w(self.alpha);
        std::f64::consts::PI - (1.0 - w * w).max(0.0).sqrt().atan2(w * self.beta.sqrt())
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None` (`Divided::jacobian_by_den` with the gradient of `den`).
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.jacobian_by_den(ray)
    }
}

impl Divided for ExtendedUnified {
    /// The ellipsoid norm `d`.
    type Parts = f64;

    /// `den = alpha d + (1 - alpha) z` with `d = sqrt(beta (x^2 + y^2) + z^2)` (Eqs. 22-24),
    /// inside `z > -w d`.
    fn den(&self, [x, y, z]: [f64; 3]) -> Option<(f64, f64)> {
        let d = (self.beta * (x * x + y * y) + z * z).sqrt();
        unified_den(self.alpha, d, z).map(|den| (den, d))
    }

    /// `dden/dp = [alpha beta x / d, alpha beta y / d, alpha z / d + 1 - alpha]`.
    fn den_gradient(&self, ray: [f64; 3], d: f64) -> [f64; 3] {
        let (a, b) = (self.alpha, self.beta);
        [
            a * b * ray[0] / d,
            a * b * ray[1] / d,
            a * ray[2] / d + (1.0 - a),
        ]
    }
}

impl CameraModel for ExtendedUnified {
    /// Eqs. 22-24 (module docs), or `None` outside `z > -w d`, for a zero or non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        self.project_by_den(ray)
    }

    /// Eqs. 26-29 (module docs); `None` outside the disc `r^2 <= 1 / (beta (2 alpha - 1))`, for a
    /// result outside the projection's domain, and for non-finite pixels.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let (a, b) = (self.alpha, self.beta);
        let (m, _) = eucm_m(&self.intrinsics, a, b, px)?;
        let ray = normalize(m)?;
        let d = (b * (ray[0] * ray[0] + ray[1] * ray[1]) + ray[2] * ray[2]).sqrt();
        (ray[2] > -unified_w(a) * d).then_some(ray)
    }

    fisheye_extent!(ExtendedUnified);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::assert_round_trips;

    /// Closed-form round trips: a few ulps of the ray (~1e-15 rad); near a fold the inverse loses
    /// ~1e-16 / (theta_max - theta) (<= 1e-12 at the 1e-4 rad margin used); 1e-11 rad is margin.
    const ANGLE_TOL: f64 = 1e-11;

    fn cam(alpha: f64, beta: f64) -> ExtendedUnified {
        ExtendedUnified::unchecked(crate::camera::tests::vga(), alpha, beta, 180.0)
    }

    #[test]
    fn theta_max_is_where_the_projection_stops() {
        for (a, b) in [(0.6, 1.2), (0.6, 0.8), (0.3, 1.5), (0.7, 0.5), (0.9, 2.0)] {
            let c = cam(a, b);
            let tm = c.theta_max();
            let (inside, outside) = (tm - 1e-6, tm + 1e-6);
            assert!(
                c.project([inside.sin(), 0.0, inside.cos()]).is_some(),
                "{a} {b}"
            );
            assert_eq!(
                c.project([outside.sin(), 0.0, outside.cos()]),
                None,
                "{a} {b}"
            );
        }
        // alpha = 0.5: the whole sphere but the backward ray.
        assert_eq!(cam(0.5, 1.3).theta_max(), std::f64::consts::PI);
        // alpha > 0.5: nothing unprojects beyond r^2 = 1 / (beta (2 alpha - 1)).
        let c = cam(0.6, 1.2);
        let r_lim = 1.0 / (1.2 * (2.0 * 0.6 - 1.0f64)).sqrt();
        assert_eq!(c.unproject([c.cx + 1.001 * r_lim * c.fx, c.cy]), None);
    }

    #[test]
    fn round_trips_up_to_theta_max() {
        for (a, b) in [(0.0, 1.0), (0.3, 1.5), (0.5, 1.0), (0.6, 1.2), (0.7, 0.5)] {
            let c = cam(a, b);
            let tm = c.theta_max().min(3.1) - 1e-4;
            let thetas = (0..=100).map(|i| tm * i as f64 / 100.0);
            let what = format!("alpha {a} beta {b}");
            assert_round_trips(&c, thetas, &[0.0, 1.0, 2.5, 4.0], ANGLE_TOL, &what);
        }
    }
}
