//! The Unified Camera Model (UCM) of Geyer and Daniilidis (ECCV 2000) and Mei and Rives (ICRA
//! 2007), in the parametrisation of Usenko et al., "The Double Sphere Camera Model", 3DV 2018
//! (Section 3.3, Eqs. 14-21; Basalt's `ucm`). A ray is projected onto the unit sphere, then
//! perspectively from a point `xi = alpha / (1 - alpha)` behind the sphere centre.
//!
//! Projection of a ray `[x, y, z]` (camera frame: x right, y down, z forward), Eq. 14:
//!
//! ```text
//! d = sqrt(x^2 + y^2 + z^2)
//! u = fx x / (alpha d + (1 - alpha) z) + cx
//! v = fy y / (alpha d + (1 - alpha) z) + cy
//! ```
//!
//! defined where `z > -w d` (Eq. 20), `w = alpha / (1 - alpha)` for `alpha <= 0.5`, else
//! `(1 - alpha) / alpha`: the angle to the optical axis is below `theta_max = acos(-w)` (180 deg
//! at `alpha = 0.5`). `alpha = 0` is the pinhole camera.
//!
//! Unprojection uses Mei's form (Mei and Rives 2007, Eq. 6), with `xi = alpha / (1 - alpha)`
//! and the focal lengths of Mei's parametrisation `gamma = f / (1 - alpha)`:
//!
//! ```text
//! mx = (1 - alpha) (u - cx) / fx,   my = (1 - alpha) (v - cy) / fy,   r^2 = mx^2 + my^2
//! eta = (xi + sqrt(1 + (1 - xi^2) r^2)) / (1 + r^2)
//! ray = [eta mx, eta my, eta - xi]
//! ```
//!
//! defined where `1 + (1 - xi^2) r^2 >= 0` (Eq. 21 of Usenko et al. in the other
//! parametrisation). This is deliberately a different formula from the Extended Unified model's
//! (`super::ExtendedUnified`, which reduces to this model at `beta = 1`), so that the two
//! cross-check each other. It needs `alpha < 1` (`xi` finite): `alpha in [0, 1)` is checked by the camera
//! file reader. Pixels are `[u, v]` = (column, row), top-left pixel centre at `(0, 0)`; radians.

use super::intrinsics::{fisheye_extent, Divided};
use super::schema::{check_rule, plain_fisheye_file, CameraFile, Checked};
use super::{CameraModel, Intrinsics};
use crate::vec3::normalize;

/// The denominator `den = alpha d + (1 - alpha) z` of the unified-model family's projection
/// (Eqs. 14, 22) for a ray with `z` and norm `d` (the model's own: Euclidean, or with `beta`),
/// or `None` outside its domain `z > -w d` (Eq. 20), for `d` zero or not finite, or `den <= 0`.
pub(super) fn unified_den(alpha: f64, d: f64, z: f64) -> Option<f64> {
    if d == 0.0 || !d.is_finite() || z <= -unified_w(alpha) * d {
        return None;
    }
    let den = alpha * d + (1.0 - alpha) * z;
    (den > 0.0).then_some(den)
}

/// `w(alpha)` of the unified-model family (Usenko et al. 2018, Eq. 20): a ray projects iff
/// `z > -w d`, with `w = alpha / (1 - alpha)` for `alpha <= 0.5` (where the denominator
/// `alpha d + (1 - alpha) z` vanishes) and `w = (1 - alpha) / alpha` above (where the projection
/// folds).
pub(super) fn unified_w(alpha: f64) -> f64 {
    if alpha <= 0.5 {
        alpha / (1.0 - alpha)
    } else {
        (1.0 - alpha) / alpha
    }
}

/// A Unified Camera Model camera (Usenko's `alpha` form). Plain parameters, nothing cached.
#[derive(Clone, Debug, PartialEq)]
pub struct Unified {
    intrinsics: Intrinsics,
    /// Model parameter in `[0, 1)`; Mei's `xi = alpha / (1 - alpha)`.
    pub alpha: f64,
    /// Full field of view of the lens, in degrees (as declared by the calibration).
    pub fov_deg: f64,
}

plain_fisheye_file!(Unified, "unified", [alpha]);

impl Unified {
    /// `alpha in [0, 1)` (part of [`Unified::validate`]).
    fn check_parameters(&self) -> Checked {
        let holds = self.alpha >= 0.0 && self.alpha < 1.0;
        let rule = "in [0, 1) (alpha = 1 puts Mei's xi at infinity)";
        check_rule("alpha", self.alpha, holds, rule)
    }

    /// Largest angle to the optical axis that projects, in radians: `acos(-w)` (exclusive).
    pub fn theta_max(&self) -> f64 {
        (-unified_w(self.alpha)).clamp(-1.0, 1.0).acos()
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None` (`Divided::jacobian_by_den` with the gradient of `den`).
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.jacobian_by_den(ray)
    }
}

impl Divided for Unified {
    /// The ray's norm `d`.
    type Parts = f64;

    /// `den = alpha d + (1 - alpha) z` with `d = |ray|` (Eq. 14), inside `z > -w d`.
    fn den(&self, [x, y, z]: [f64; 3]) -> Option<(f64, f64)> {
        let d = x.hypot(y).hypot(z);
        unified_den(self.alpha, d, z).map(|den| (den, d))
    }

    /// `dden/dp = alpha p / d + (1 - alpha) e_z`.
    fn den_gradient(&self, ray: [f64; 3], d: f64) -> [f64; 3] {
        let a = self.alpha;
        [a * ray[0] / d, a * ray[1] / d, a * ray[2] / d + (1.0 - a)]
    }
}

impl CameraModel for Unified {
    /// Eq. 14 (module docs), or `None` outside `z > -w |ray|`, for a zero or non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        self.project_by_den(ray)
    }

    /// Mei's closed form (module docs), normalised; `None` where its square root is imaginary,
    /// for a result outside the projection's domain, and for non-finite pixels or `alpha >= 1`.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let a = self.alpha;
        if a.is_nan() || a >= 1.0 {
            return None;
        }
        let xi = a / (1.0 - a);
        let mx = (1.0 - a) * (px[0] - self.cx) / self.fx;
        let my = (1.0 - a) * (px[1] - self.cy) / self.fy;
        let r2 = mx * mx + my * my;
        let disc = 1.0 + (1.0 - xi * xi) * r2;
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let eta = (xi + disc.sqrt()) / (1.0 + r2);
        let ray = normalize([eta * mx, eta * my, eta - xi])?;
        (ray[2] > -unified_w(a)).then_some(ray)
    }

    fisheye_extent!(Unified);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::assert_round_trips;

    /// Closed-form round trips: a few ulps of the ray (~1e-15 rad); 1e-12 rad is margin.
    const ANGLE_TOL: f64 = 1e-12;

    fn cam(alpha: f64) -> Unified {
        Unified::unchecked(crate::camera::tests::vga(), alpha, 180.0)
    }

    #[test]
    fn theta_max_and_domain() {
        // alpha = 0.5: the whole sphere but the backward ray.
        let c = cam(0.5);
        assert_eq!(c.theta_max(), std::f64::consts::PI);
        assert!(c.project([0.1, 0.0, -1.0]).is_some());
        assert_eq!(c.project([0.0, 0.0, -1.0]), None);
        // alpha = 0.6: w = 2/3, theta_max = acos(-2/3) ~ 131.8 deg; the projection folds there.
        let c = cam(0.6);
        let tm = c.theta_max();
        assert!((tm - (-2.0f64 / 3.0).acos()).abs() < 1e-15);
        assert!(c
            .project([(tm - 1e-6).sin(), 0.0, (tm - 1e-6).cos()])
            .is_some());
        assert_eq!(c.project([(tm + 1e-6).sin(), 0.0, (tm + 1e-6).cos()]), None);
        // Beyond the edge of the image disc r^2 <= 1 / (2 alpha - 1) nothing unprojects.
        let r_lim = 1.0 / (2.0 * 0.6 - 1.0f64).sqrt();
        assert_eq!(c.unproject([c.cx + 1.001 * r_lim * c.fx, c.cy]), None);
        assert!(c.unproject([c.cx + 0.999 * r_lim * c.fx, c.cy]).is_some());
        // alpha = 0.3: the denominator vanishes at cos(theta) = -3/7; every pixel unprojects.
        let c = cam(0.3);
        assert!((c.theta_max() - (-3.0f64 / 7.0).acos()).abs() < 1e-15);
        assert!(c.unproject([1e7, -1e7]).is_some());
    }

    #[test]
    fn round_trips_up_to_theta_max() {
        for alpha in [0.0, 0.3, 0.5, 0.6, 0.8] {
            let c = cam(alpha);
            let tm = c.theta_max().min(3.1);
            let thetas = (0..=100).map(|i| tm * i as f64 / 100.0 * 0.9999);
            let what = format!("alpha {alpha}");
            assert_round_trips(&c, thetas, &[0.0, 1.0, 2.5, 4.0], ANGLE_TOL, &what);
        }
    }

    #[test]
    fn unified_w_is_continuous_at_one_half() {
        assert_eq!(unified_w(0.5), 1.0);
        assert!((unified_w(0.5 + 1e-12) - 1.0).abs() < 1e-11);
        assert_eq!(unified_w(0.0), 0.0);
        assert_eq!(unified_w(1.0), 0.0);
    }
}
