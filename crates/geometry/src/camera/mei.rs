//! Mei's unified model with radial-tangential distortion (Mei and Rives, "Single View Point
//! Omnidirectional Camera Calibration from Planar Grids", ICRA 2007; Kalibr's `omni-radtan`,
//! camodocal's `MEI`). A ray is projected onto the unit sphere, then perspectively from a point
//! `xi` behind the sphere centre onto a plane, where the radial-tangential distortion of
//! [`super::radtan`] (`k1 k2 p1 p2`) acts before the focal lengths.
//!
//! Projection of a ray `[x, y, z]` (camera frame: x right, y down, z forward), as Kalibr's
//! `OmniProjection::euclideanToKeypoint`:
//!
//! ```text
//! d = sqrt(x^2 + y^2 + z^2)
//! m = [x, y] / (z + xi d)                       (Mei 2007, Eq. 1-3)
//! m'' = radtan(m)                               (k1, k2, p1, p2; super::radtan)
//! u = fx m''_x + cx,   v = fy m''_y + cy        (fx, fy: Mei's gamma1, gamma2; Kalibr's fu, fv)
//! ```
//!
//! defined where `z > -w d` with `w = xi` for `xi <= 1`, else `1 / xi` (Kalibr's
//! `fov_parameter`), and where `m` lies in the distortion's invertible domain. Without
//! distortion this is the `unified` model with `alpha = xi / (1 + xi)` and
//! `f = fx / (1 + xi)`; a different formula, so that the two cross-check each other.
//!
//! Unprojection undistorts `m''` (Newton with a residual check: a pixel it cannot invert is
//! `None`), then lifts `m` onto the sphere in closed form (Kalibr's `keypointToEuclidean`,
//! Mei 2007 Eq. 6), defined for `xi <= 1` or `|m|^2 <= 1 / (xi^2 - 1)`:
//!
//! ```text
//! r^2 = |m|^2,   ray = [m_x, m_y, 1 - xi (r^2 + 1) / (xi + sqrt(1 + (1 - xi^2) r^2))]
//! ```
//!
//! Parameters: `xi >= 0`. Pixels are `[u, v]` = (column, row), top-left pixel centre at `(0, 0)`;
//! radians.

use super::intrinsics::{deref_intrinsics, eq_by_fields, fisheye_extent};
use super::radtan::RadTan;
use super::schema::{check_fov_in_domain, check_rule, checked, raw_camera_file, CameraFile, Checked, Invalid};
use super::{CameraModel, Intrinsics};
use crate::vec3::{finite3, normalize};

/// A camera of Mei's unified model with radial-tangential distortion.
///
/// Build it with [`Mei::new`]. Equality compares the public fields only (the distortion's
/// domain is a function of them).
#[derive(Clone, Debug)]
pub struct Mei {
    intrinsics: Intrinsics,
    /// Distance of the projection centre behind the sphere centre (Mei's `xi`), `>= 0`.
    pub xi: f64,
    /// Radial coefficients `[k1, k2]`.
    pub k: [f64; 2],
    /// Tangential coefficients `[p1, p2]`.
    pub p: [f64; 2],
    /// Full field of view of the lens, in degrees.
    pub fov_deg: f64,
    /// The distortion with its domain.
    distortion: RadTan,
}

deref_intrinsics!(Mei);

eq_by_fields!(Mei: intrinsics, xi, k, p, fov_deg);

raw_camera_file! {
    /// A `mei` camera file as written.
    fisheye struct Raw {
        xi: f64,
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
    }
}

impl CameraFile for Mei {
    const MODEL: &'static str = "mei";
    type Raw = Raw;
    fn fields(&self) -> Vec<(&'static str, f64)> {
        let ([k1, k2], [p1, p2]) = (self.k, self.p);
        let params = [("xi", self.xi), ("k1", k1), ("k2", k2), ("p1", p1), ("p2", p2)];
        self.intrinsics.with_fov(self.fov_deg, &params)
    }
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        Mei::new(r.intrinsics(), r.xi, [r.k1, r.k2], [r.p1, r.p2], r.fov_deg)
    }
}

impl Mei {
    /// A checked camera (see [`Mei::validate`]).
    pub fn new(
        intrinsics: Intrinsics,
        xi: f64,
        k: [f64; 2],
        p: [f64; 2],
        fov_deg: f64,
    ) -> Result<Self, Invalid> {
        checked(Self::unchecked(intrinsics, xi, k, p, fov_deg), Self::validate)
    }

    /// The camera without the checks: for probing the model's domain before its field of view
    /// is known.
    pub(crate) fn unchecked(
        intrinsics: Intrinsics,
        xi: f64,
        k: [f64; 2],
        p: [f64; 2],
        fov_deg: f64,
    ) -> Self {
        Mei {
            intrinsics,
            xi,
            k,
            p,
            fov_deg,
            distortion: RadTan::new([k[0], k[1], 0.0, 0.0, 0.0, 0.0], p, 0.0),
        }
    }

    /// Every float finite, the intrinsics ([`Intrinsics::validate`]), `0 < fov_deg < 360`,
    /// `xi >= 0`, and `fov_deg / 2` below [`Mei::theta_max`]; the error names the field.
    pub fn validate(&self) -> Checked {
        self.intrinsics
            .validate_fisheye(&self.fields(), self.fov_deg)?;
        check_rule("xi", self.xi, self.xi >= 0.0, ">= 0")?;
        check_fov_in_domain(self.fov_deg, self.theta_max(), "xi, k1, k2")
    }

    /// `w` of the projection's domain `z > -w |ray|`: `xi` for `xi <= 1`, else `1 / xi`.
    fn w(&self) -> f64 {
        if self.xi <= 1.0 {
            self.xi
        } else {
            1.0 / self.xi
        }
    }

    /// Largest angle to the optical axis that projects (radians, exclusive), radially: the
    /// smaller of `acos(-w)` and the angle whose `|m| = sin(theta) / (cos(theta) + xi)` reaches
    /// the distortion's fold `r_max`, `theta = atan(r) + asin(r xi / sqrt(1 + r^2))`.
    pub fn theta_max(&self) -> f64 {
        let sphere = (-self.w()).clamp(-1.0, 1.0).acos();
        let r = self.distortion.r_max;
        if !r.is_finite() {
            return sphere;
        }
        let fold = r.atan() + (r * self.xi / r.hypot(1.0)).min(1.0).asin();
        sphere.min(fold)
    }

    /// The undistorted point `m` of a ray and its denominator `z + xi d`, or `None` outside the
    /// projection's domain.
    fn mei_point(&self, ray: [f64; 3]) -> Option<([f64; 2], f64, f64)> {
        if !finite3(ray) {
            return None;
        }
        let [x, y, z] = ray;
        let d = x.hypot(y).hypot(z);
        if d == 0.0 || z <= -self.w() * d {
            return None;
        }
        let den = z + self.xi * d;
        if den <= 0.0 {
            return None;
        }
        let m = [x / den, y / den];
        self.distortion.in_domain(m).then_some((m, den, d))
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None`: `diag(fx, fy) D dm/dp` with `D` the distortion Jacobian and
    /// `dm/dp = e / den - m dden/dp / den`, `dden/dp = xi p / d + e_z`.
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        let (m, den, d) = self.mei_point(ray)?;
        let dden = [
            self.xi * ray[0] / d,
            self.xi * ray[1] / d,
            self.xi * ray[2] / d + 1.0,
        ];
        let dm = [0, 1].map(|r| {
            [0, 1, 2].map(|c| {
                let e = if r == c { 1.0 } else { 0.0 };
                (e - m[r] * dden[c]) / den
            })
        });
        let j = self.distortion.jacobian(m);
        let f = [self.fx, self.fy];
        Some([0, 1].map(|r| [0, 1, 2].map(|c| f[r] * (j[r][0] * dm[0][c] + j[r][1] * dm[1][c]))))
    }
}

impl CameraModel for Mei {
    /// Kalibr's projection (module docs), or `None` outside `z > -w |ray|`, past the
    /// distortion's fold, for a zero or non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        let (m, _, _) = self.mei_point(ray)?;
        let [xd, yd] = self.distortion.distort(m);
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// Undistorts (Newton with a residual check), then Mei's lift (module docs); `None` past
    /// the fold, outside the lift's disc, or for a result outside the projection's domain.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let target = [(px[0] - self.cx) / self.fx, (px[1] - self.cy) / self.fy];
        let (m, _) = self.distortion.undistort(target)?;
        let xi = self.xi;
        let r2 = m[0] * m[0] + m[1] * m[1];
        let disc = 1.0 + (1.0 - xi * xi) * r2;
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let z = 1.0 - xi * (r2 + 1.0) / (xi + disc.sqrt());
        let ray = normalize([m[0], m[1], z])?;
        (ray[2] > -self.w()).then_some(ray)
    }

    fisheye_extent!(Mei);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::{angle, assert_jacobian_matches_central_differences, vga};
    use crate::camera::Unified;

    /// Newton to a residual below 1e-10 normalised units (~1e-12 in practice) and a closed-form
    /// lift: the round trip is ~1e-12 px; 1e-9 px is margin.
    const PX_TOL: f64 = 1e-9;
    /// Two closed forms of the same map: round-off, ~1e-15 rad; 1e-12 is margin.
    const ANGLE_TOL: f64 = 1e-12;

    fn cam(xi: f64, k: [f64; 2], p: [f64; 2]) -> Mei {
        Mei::unchecked(vga(), xi, k, p, 180.0)
    }

    #[test]
    fn without_distortion_it_is_the_unified_model() {
        for xi in [0.0, 0.5, 1.0, 1.6] {
            let mei = cam(xi, [0.0; 2], [0.0; 2]);
            let f = [mei.fx / (1.0 + xi), mei.fy / (1.0 + xi), mei.cx, mei.cy];
            let intrinsics = Intrinsics::from_parts(f, mei.size());
            let ucm = Unified::unchecked(intrinsics, xi / (1.0 + xi), 180.0);
            assert!((mei.theta_max() - ucm.theta_max()).abs() < 1e-15, "{xi}");
            for i in 0..60 {
                let t = mei.theta_max().min(3.1) * i as f64 / 60.0;
                let ray = [t.sin() * 0.6, t.sin() * 0.8, t.cos()];
                let (a, b) = (mei.project(ray).unwrap(), ucm.project(ray).unwrap());
                assert!((a[0] - b[0]).hypot(a[1] - b[1]) < PX_TOL, "{xi} {t}");
                let (ra, rb) = (mei.unproject(a).unwrap(), ucm.unproject(a).unwrap());
                assert!(angle(ra, rb) < ANGLE_TOL, "{xi} {t}");
            }
        }
    }

    #[test]
    fn round_trips_with_distortion_and_none_past_the_fold() {
        let c = cam(1.2, [-0.2, 0.05], [0.001, -0.0005]);
        let mut inside = 0;
        for v in (-200..700).step_by(13) {
            for u in (-200..900).step_by(13) {
                let px = [u as f64, v as f64];
                if let Some(ray) = c.unproject(px) {
                    let back = c.project(ray).unwrap();
                    assert!((back[0] - px[0]).hypot(back[1] - px[1]) < PX_TOL, "{px:?}");
                    inside += 1;
                }
            }
        }
        assert!(inside > 1000, "{inside}");
        // Beyond theta_max nothing projects.
        let t = c.theta_max() + 1e-6;
        assert_eq!(c.project([t.sin(), 0.0, t.cos()]), None);
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let c = cam(0.9, [-0.2, 0.05], [0.001, -0.0005]);
        let rays = [[0.1, -0.2, 1.0], [0.5, 0.3, 0.4], [-0.7, 0.2, 0.1]];
        assert_jacobian_matches_central_differences(&c, |ray| c.project_jacobian(ray), &rays);
    }
}
