//! The Double Sphere camera model of Usenko, Demmel and Cremers, "The Double Sphere Camera
//! Model", 3DV 2018 (Section 3.6, Eqs. 40-47; the same model as Basalt's `ds` and Kalibr's `ds`
//! camera). A ray is projected onto two unit spheres whose centres are `xi` apart, then with the
//! unified model of parameter `alpha`.
//!
//! Projection of a ray `[x, y, z]` (camera frame: x right, y down, z forward), Eq. 40-42:
//!
//! ```text
//! d1 = sqrt(x^2 + y^2 + z^2)
//! d2 = sqrt(x^2 + y^2 + (xi d1 + z)^2)
//! u  = fx x / (alpha d2 + (1 - alpha) (xi d1 + z)) + cx
//! v  = fy y / (alpha d2 + (1 - alpha) (xi d1 + z)) + cy
//! ```
//!
//! defined where `z > -w2 d1` (Eq. 43), with
//! `w1 = alpha / (1 - alpha)` if `alpha <= 0.5`, else `(1 - alpha) / alpha`, and
//! `w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)`: the angle to the optical axis is at most
//! `theta_max = acos(-w2)`, past 90 degrees whenever `w2 > 0`.
//!
//! Unprojection of a pixel, Eqs. 44-47 (closed form):
//!
//! ```text
//! mx = (u - cx) / fx,  my = (v - cy) / fy,  r^2 = mx^2 + my^2
//! mz = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)
//! ray = (mz xi + sqrt(mz^2 + (1 - xi^2) r^2)) / (mz^2 + r^2) [mx, my, mz] - [0, 0, xi]
//! ```
//!
//! defined for `r^2 <= 1 / (2 alpha - 1)` when `alpha > 0.5` (Eq. 47). That disc reaches slightly
//! past the image of `theta_max`, so [`CameraModel::unproject`] also rejects a result outside the
//! projection's domain: every pixel it accepts round-trips.
//!
//! Parameters: `xi in (-1, 1]`, `alpha in [0, 1]` (checked by the camera file reader). Pixels are
//! `[u, v]` = (column, row) with the centre of the top-left pixel at `(0, 0)`; angles in radians.

use super::extended_unified::eucm_m;
use super::intrinsics::{fisheye_extent, Divided};
use super::schema::{
    check_rule, check_unit_interval, plain_fisheye_file, CameraFile, Checked,
};
use super::unified::unified_w;
use super::{CameraModel, Intrinsics};
use crate::vec3::normalize;

/// A Double Sphere camera. All fields are plain parameters (nothing derived is cached).
#[derive(Clone, Debug, PartialEq)]
pub struct DoubleSphere {
    intrinsics: Intrinsics,
    /// Distance between the two sphere centres (unit-sphere radii).
    pub xi: f64,
    /// Weight of the second projection step (0: pinhole step, 0.5: stereographic-like).
    pub alpha: f64,
    /// Full field of view of the lens, in degrees (as declared by the calibration).
    pub fov_deg: f64,
}

plain_fisheye_file!(DoubleSphere, "double-sphere", [xi, alpha]);

impl DoubleSphere {
    /// `xi in (-1, 1]` and `alpha in [0, 1]` (part of [`DoubleSphere::validate`]).
    fn check_parameters(&self) -> Checked {
        let xi_holds = self.xi > -1.0 && self.xi <= 1.0;
        check_rule("xi", self.xi, xi_holds, "in (-1, 1]")?;
        check_unit_interval("alpha", self.alpha)
    }

    /// `w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)` of Eq. 43: rays project iff `z > -w2 |ray|`.
    pub fn w2(&self) -> f64 {
        let w1 = unified_w(self.alpha);
        (w1 + self.xi) / (2.0 * w1 * self.xi + self.xi * self.xi + 1.0).sqrt()
    }

    /// Largest angle to the optical axis that projects, in radians: `acos(-w2)` (exclusive).
    pub fn theta_max(&self) -> f64 {
        (-self.w2()).clamp(-1.0, 1.0).acos()
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None` (`Divided::jacobian_by_den` with the gradient of `den`).
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.jacobian_by_den(ray)
    }
}

impl Divided for DoubleSphere {
    /// `(d1, k = xi d1 + z, d2)`.
    type Parts = (f64, f64, f64);

    /// `den = alpha d2 + (1 - alpha) k` (Eqs. 40-42), inside `z > -w2 d1`.
    fn den(&self, [x, y, z]: [f64; 3]) -> Option<(f64, (f64, f64, f64))> {
        let d1 = x.hypot(y).hypot(z);
        if d1 == 0.0 || !d1.is_finite() || z <= -self.w2() * d1 {
            return None;
        }
        let k = self.xi * d1 + z;
        let d2 = x.hypot(y).hypot(k);
        let den = self.alpha * d2 + (1.0 - self.alpha) * k;
        (den > 0.0).then_some((den, (d1, k, d2)))
    }

    /// With `k = xi d1 + z`:
    ///
    /// ```text
    /// dk/dx = xi x / d1          dk/dy = xi y / d1          dk/dz = xi z / d1 + 1
    /// dd2/dx = (x + k dk/dx) / d2   dd2/dy = (y + k dk/dy) / d2   dd2/dz = k dk/dz / d2
    /// dden = alpha dd2 + (1 - alpha) dk
    /// ```
    fn den_gradient(&self, [x, y, z]: [f64; 3], (d1, k, d2): (f64, f64, f64)) -> [f64; 3] {
        let dk = [self.xi * x / d1, self.xi * y / d1, self.xi * z / d1 + 1.0];
        let dd2 = [(x + k * dk[0]) / d2, (y + k * dk[1]) / d2, k * dk[2] / d2];
        [0, 1, 2].map(|i| self.alpha * dd2[i] + (1.0 - self.alpha) * dk[i])
    }
}

impl CameraModel for DoubleSphere {
    /// Eqs. 40-42 (module docs), or `None` outside `z > -w2 |ray|`, for a zero or non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        self.project_by_den(ray)
    }

    /// Eqs. 44-47 (module docs), normalised; `None` outside the disc `r^2 <= 1 / (2 alpha - 1)`,
    /// for a result outside the projection's domain, and for non-finite pixels.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let (a, xi) = (self.alpha, self.xi);
        let ([mx, my, mz], r2) = eucm_m(&self.intrinsics, a, 1.0, px)?;
        let disc2 = mz * mz + (1.0 - xi * xi) * r2;
        if disc2.is_nan() || disc2 < 0.0 {
            return None;
        }
        let s = (mz * xi + disc2.sqrt()) / (mz * mz + r2);
        let ray = normalize([s * mx, s * my, s * mz - xi])?;
        (ray[2] > -self.w2()).then_some(ray)
    }

    fisheye_extent!(DoubleSphere);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::assert_round_trips;
    use crate::vec3::angle_to_axis;

    /// Closed-form round trips: a few ulps of the ray (~1e-15 rad); 1e-12 rad is margin.
    const ANGLE_TOL: f64 = 1e-12;

    /// Rounded values of the kind Basalt reports for a TUM-VI 512x512 fisheye (illustrative).
    fn cam() -> DoubleSphere {
        DoubleSphere {
            intrinsics: Intrinsics {
                fx: 158.28,
                fy: 158.27,
                cx: 254.96,
                cy: 256.88,
                width: 512,
                height: 512,
            },
            xi: -0.172,
            alpha: 0.593,
            fov_deg: 190.0,
        }
    }

    #[test]
    fn theta_max_matches_the_paper_condition() {
        // w1 = 0.407 / 0.593, w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1).
        let c = cam();
        let w1 = 0.407f64 / 0.593;
        let w2 = (w1 - 0.172) / (2.0 * w1 * -0.172 + 0.172f64.powi(2) + 1.0).sqrt();
        assert!((c.w2() - w2).abs() < ANGLE_TOL);
        let tm = c.theta_max();
        // About 125 deg: past 90 degrees.
        assert!(
            tm > 120f64.to_radians() && tm < 130f64.to_radians(),
            "{}",
            tm.to_degrees()
        );
        let inside = tm - 1e-6;
        let outside = tm + 1e-6;
        assert!(c.project([inside.sin(), 0.0, inside.cos()]).is_some());
        assert_eq!(c.project([outside.sin(), 0.0, outside.cos()]), None);
    }

    #[test]
    fn pixels_past_the_domain_edge_do_not_unproject() {
        let c = cam();
        // r^2 <= 1 / (2 alpha - 1) is the closed form's own limit ...
        let r_lim = 1.0 / (2.0 * c.alpha - 1.0f64).sqrt();
        assert_eq!(c.unproject([c.cx + 1.001 * r_lim * c.fx, c.cy]), None);
        // ... but the image of theta_max lies slightly inside it: the ring between is rejected.
        let tm = c.theta_max() - 1e-9;
        let edge = c.project([tm.sin(), 0.0, tm.cos()]).unwrap()[0] - c.cx;
        assert!(edge < r_lim * c.fx);
        let between = 0.5 * (edge + r_lim * c.fx);
        assert_eq!(c.unproject([c.cx + between, c.cy]), None);
        let ray = c.unproject([c.cx + 0.999 * edge, c.cy]).unwrap();
        assert!(angle_to_axis(ray) < c.theta_max());
    }

    #[test]
    fn round_trips_up_to_theta_max() {
        let c = cam();
        let tm = c.theta_max();
        let thetas = (0..=100).map(|i| tm * i as f64 / 100.0 * 0.999_999);
        assert_round_trips(&c, thetas, &[0.0, 1.0, 2.5, 4.0], ANGLE_TOL, "TUM-VI-like");
    }
}
