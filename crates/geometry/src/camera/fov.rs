//! The field-of-view (FOV) model of Devernay and Faugeras, "Straight lines have to be
//! straight", Machine Vision and Applications 13, 2001 (Section 2.3, Eqs. 13-14; Kalibr's
//! `pinhole-fov`, COLMAP's `FOV`, Basalt's `fov`): one parameter `w`, the field of view of the
//! ideal fish-eye lens the model describes.
//!
//! With `r_u = tan(theta)` the undistorted radius on the `z = 1` plane and `r_d` the distorted
//! one (normalised units),
//!
//! ```text
//! r_d = atan(2 r_u tan(w / 2)) / w                 (Eq. 13)
//! r_u = tan(r_d w) / (2 tan(w / 2))                (Eq. 14)
//! u = fx r_d cos(phi) + cx,   v = fy r_d sin(phi) + cy
//! ```
//!
//! Here the angle `alpha = r_d w` is computed as `atan2(2 tan(w / 2) sin(theta), cos(theta))`,
//! which equals Eq. 13 for rays in front of the camera (`z > 0`, where Kalibr's pinhole-fov is
//! defined) and continues it, increasing, up to `theta -> pi`: rays past 90 degrees project, as
//! in Basalt's `fov`. The inverse is closed form, `theta = atan2(sin(alpha), 2 tan(w / 2)
//! cos(alpha))`, for `alpha < pi`; it is checked against the forward map before it answers.
//!
//! Parameters: `0 < w < pi`. Pixels are `[u, v]` = (column, row), top-left pixel centre at
//! `(0, 0)`; radians.

use std::f64::consts::PI;

use super::intrinsics::fisheye_extent;
use super::schema::{check_rule, plain_fisheye_file, CameraFile, Checked};
use super::{CameraModel, Intrinsics};
use crate::vec3::project_off_axis;

/// The largest disagreement (normalised units) between a pixel's `r_d` and the forward map of
/// the ray its closed-form inverse gives: times a focal length up to 1e4 px it is 1e-6 px, the
/// accuracy the imports are checked to; round-off is ~1e-15.
pub const RESIDUAL_TOL: f64 = 1e-10;

/// A camera of the FOV model. Plain parameters, nothing cached.
#[derive(Clone, Debug, PartialEq)]
pub struct Fov {
    intrinsics: Intrinsics,
    /// The model's field-of-view parameter `w`, radians, in `(0, pi)`.
    pub w: f64,
    /// Full field of view of the lens, in degrees.
    pub fov_deg: f64,
}

plain_fisheye_file!(Fov, "fov", [w]);

impl Fov {
    /// `0 < w < pi` (part of [`Fov::validate`]).
    fn check_parameters(&self) -> Checked {
        let holds = self.w > 0.0 && self.w < PI;
        check_rule("w", self.w, holds, "in (0, pi) radians")
    }

    /// Largest angle to the optical axis that projects, in radians: `pi` (exclusive; every ray
    /// but the backward one).
    pub fn theta_max(&self) -> f64 {
        PI
    }

    /// `2 tan(w / 2)`.
    fn two_tan(&self) -> f64 {
        2.0 * (self.w / 2.0).tan()
    }

    /// `alpha = r_d w` of a ray at radius `q = sqrt(x^2 + y^2)` and depth `z`.
    fn alpha(&self, q: f64, z: f64) -> f64 {
        (self.two_tan() * q).atan2(z)
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None`. With `u = fx x g + cx`, `g = alpha / (w q)`, `T = 2 tan(w/2)`:
    /// `dalpha/dq = T z / (z^2 + T^2 q^2)`, `dalpha/dz = -T q / (z^2 + T^2 q^2)`,
    /// `dg/dq = (q dalpha/dq - alpha) / (w q^2)`, `dg/dz = dalpha/dz / (w q)`; on the axis
    /// `g = T / (w z)` with zero derivatives.
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        let q = x.hypot(y);
        let t = self.two_tan();
        let w = self.w;
        let row = |f: f64, c: f64, axis: usize| -> [f64; 3] {
            if q == 0.0 {
                let g = t / (w * z);
                let mut r = [0.0; 3];
                r[axis] = f * g;
                return r;
            }
            let alpha = self.alpha(q, z);
            let g = alpha / (w * q);
            let den = z * z + t * t * q * q;
            let dg_dq = (q * t * z / den - alpha) / (w * q * q);
            let dg_dz = -t * q / den / (w * q);
            let e = |i: usize| if i == axis { 1.0 } else { 0.0 };
            [
                f * (e(0) * g + c * dg_dq * x / q),
                f * (e(1) * g + c * dg_dq * y / q),
                f * c * dg_dz,
            ]
        };
        Some([row(self.fx, x, 0), row(self.fy, y, 1)])
    }
}

impl CameraModel for Fov {
    /// Eq. 13 in its angle form (module docs); `None` for a zero, non-finite or backward ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        project_off_axis(ray, [self.cx, self.cy], |[x, y, z], q| {
            let g = self.alpha(q, z) / (self.w * q);
            Some([self.fx * x * g + self.cx, self.fy * y * g + self.cy])
        })
    }

    /// Eq. 14 in its angle form (module docs); `None` for `r_d w >= pi`, non-finite pixels, or
    /// a ray whose forward map misses `r_d` by more than `RESIDUAL_TOL`.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let mx = (px[0] - self.cx) / self.fx;
        let my = (px[1] - self.cy) / self.fy;
        let r_d = mx.hypot(my);
        if !r_d.is_finite() {
            return None;
        }
        if r_d == 0.0 {
            return Some([0.0, 0.0, 1.0]);
        }
        let alpha = r_d * self.w;
        if alpha >= PI {
            return None;
        }
        let (sa, ca) = alpha.sin_cos();
        let theta = sa.atan2(self.two_tan() * ca);
        let (s, c) = theta.sin_cos();
        if (self.alpha(s, c) / self.w - r_d).abs() > RESIDUAL_TOL {
            return None;
        }
        Some([s * mx / r_d, s * my / r_d, c])
    }

    fisheye_extent!(Fov);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::{
        assert_jacobian_matches_central_differences, assert_round_trips, vga,
    };

    /// Closed-form round trips: a few ulps of the ray (~1e-15 rad); 1e-12 rad is margin.
    const ANGLE_TOL: f64 = 1e-12;

    fn cam(w: f64) -> Fov {
        Fov::unchecked(vga(), w, 180.0)
    }

    #[test]
    fn eq_13_in_front_and_round_trips_past_90_degrees() {
        for w in [0.3, 0.9, 1.7, 3.0] {
            let c = cam(w);
            // Eq. 13 on the z = 1 plane.
            for r_u in [0.01, 0.4, 1.0, 3.0] {
                let r_d = (2.0 * r_u * (w / 2.0).tan()).atan() / w;
                let p = c.project([r_u, 0.0, 1.0]).unwrap();
                assert!((p[0] - (c.cx + c.fx * r_d)).abs() < 1e-9, "{w} {r_u}");
            }
            let thetas = (0..100).map(|i| 3.1 * i as f64 / 100.0);
            assert_round_trips(&c, thetas, &[0.0, 1.0, 2.5, 4.0], ANGLE_TOL, "fov");
        }
        assert_eq!(cam(0.9).project([0.0, 0.0, -1.0]), None);
        // Past r_d w = pi nothing unprojects.
        let c = cam(0.9);
        assert_eq!(c.unproject([c.cx + c.fx * PI / 0.9 * 1.001, c.cy]), None);
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let c = cam(0.9);
        let rays = [
            [0.1, -0.2, 1.0],
            [0.5, 0.3, 0.4],
            [-0.7, 0.2, -0.3],
            [0.0, 0.0, 2.0],
        ];
        assert_jacobian_matches_central_differences(&c, |ray| c.project_jacobian(ray), &rays);
    }
}
