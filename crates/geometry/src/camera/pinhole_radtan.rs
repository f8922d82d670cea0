//! The pinhole camera with radial-tangential ("plumb bob", Brown-Conrady) distortion: OpenCV's
//! standard model with 5 or 8 coefficients `k1, k2, p1, p2, k3[, k4, k5, k6]` (OpenCV `calib3d`
//! documentation, "Detailed description"; Kalibr's `pinhole-radtan` with `k3 = 0`; COLMAP's
//! `OPENCV` and `FULL_OPENCV`; Basalt's `pinhole-radtan8`, whose `rpmax` bounds the domain).
//!
//! Projection of a ray `[x, y, z]` with `z > 0` (camera frame: x right, y down, z forward):
//!
//! ```text
//! x' = x / z,  y' = y / z,  s = r^2 = x'^2 + y'^2
//! R = (1 + k1 s + k2 s^2 + k3 s^3) / (1 + k4 s + k5 s^2 + k6 s^3)
//! x'' = x' R + 2 p1 x' y' + p2 (s + 2 x'^2)
//! y'' = y' R + p1 (s + 2 y'^2) + 2 p2 x' y'
//! u = fx x'' + cx,   v = fy y'' + cy
//! ```
//!
//! The distortion and its inverse are the shared [`super::radtan`] module's: the model is
//! defined where the distortion does not fold (`r <= r_max` and a positive Jacobian
//! determinant, `r_max` also bounded by `rpmax` when that is > 0). A distortion that folds
//! inside the image is a valid camera whose pixels past the fold are outside the model
//! (`unproject` is `None` there, as outside a fisheye's field of view); `calibconv camera
//! import` reports how much of the image that is. Unprojection is Newton's method with a
//! residual check: a pixel it cannot invert is `None`, never a wrong ray.
//!
//! The field of view is derived: the angle between the rays of the left and right image edges
//! (`u = -0.5` and `u = width - 0.5`) on the principal row, or, where an edge lies past the
//! fold, of the last pixel towards it that unprojects. Pixels are `[u, v]` = (column, row),
//! top-left pixel centre at `(0, 0)`; radians.

use super::intrinsics::{deref_intrinsics, eq_by_fields};
use super::radtan::RadTan;
use super::schema::{
    check_finite, check_rule, checked, raw_camera_file, CameraFile, Checked, Invalid,
};
use super::solve::last_ok;
use super::{Camera, CameraModel, Intrinsics, PixelConvention};
use crate::vec3::{finite3, normalize};

/// Points on the principal row between the principal point and an image edge past the fold,
/// scanned for the last one that unprojects before bisecting to it.
const EDGE_SCAN_STEPS: usize = 64;

/// A pinhole camera with OpenCV radial-tangential distortion (5 or 8 coefficients).
///
/// Build it with [`PinholeRadTan::new`] or [`PinholeRadTan::rational`], which find the radial
/// range `r_max` and the field of view. Equality compares the public fields only (the derived
/// values are functions of them).
#[derive(Clone, Debug)]
pub struct PinholeRadTan {
    intrinsics: Intrinsics,
    /// Radial numerator coefficients `[k1, k2, k3]` (of `r^2`, `r^4`, `r^6`).
    pub k: [f64; 3],
    /// Tangential coefficients `[p1, p2]`.
    pub p: [f64; 2],
    /// Radial denominator coefficients `[k4, k5, k6]` (OpenCV's rational model; zero for the
    /// 5-coefficient model).
    pub k_den: [f64; 3],
    /// A bound on the undistorted radius `x'^2 + y'^2 <= rpmax^2` given by the source (Basalt's
    /// `rpmax`); 0 for none.
    pub rpmax: f64,
    /// The distortion with its domain.
    distortion: RadTan,
    /// Edge-to-edge horizontal field of view, radians.
    fov: f64,
}

deref_intrinsics!(PinholeRadTan);

eq_by_fields!(PinholeRadTan: intrinsics, k, p, k_den, rpmax);

raw_camera_file! {
    /// A pinhole camera with OpenCV radial-tangential distortion, as written; `k4 k5 k6` and
    /// `rpmax` are optional (0 when absent).
    pinhole struct Raw {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
        #[serde(default)]
        k4: f64,
        #[serde(default)]
        k5: f64,
        #[serde(default)]
        k6: f64,
        #[serde(default)]
        rpmax: f64,
    }
}

impl CameraFile for PinholeRadTan {
    const MODEL: &'static str = "pinhole-radtan";
    type Raw = Raw;
    /// `fx fy cx cy k1 k2 p1 p2 k3`, then `k4 k5 k6` when any is non-zero and `rpmax` when
    /// non-zero (so 5-coefficient files stay as they were).
    fn fields(&self) -> Vec<(&'static str, f64)> {
        let ([k1, k2, k3], [p1, p2], [k4, k5, k6]) = (self.k, self.p, self.k_den);
        let mut fields = self.intrinsics.fields().to_vec();
        fields.extend([("k1", k1), ("k2", k2), ("p1", p1), ("p2", p2), ("k3", k3)]);
        if self.k_den != [0.0; 3] {
            fields.extend([("k4", k4), ("k5", k5), ("k6", k6)]);
        }
        if self.rpmax != 0.0 {
            fields.push(("rpmax", self.rpmax));
        }
        fields
    }
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        let k = [r.k1, r.k2, r.k3, r.k4, r.k5, r.k6];
        PinholeRadTan::rational(r.intrinsics(), k, [r.p1, r.p2], r.rpmax)
    }
}

impl PinholeRadTan {
    /// A checked camera (see [`PinholeRadTan::validate`]) with OpenCV's 5 coefficients
    /// `k = [k1, k2, k3]`, `p = [p1, p2]`; computes `r_max` and the field of view.
    pub fn new(intrinsics: Intrinsics, k: [f64; 3], p: [f64; 2]) -> Result<Self, Invalid> {
        Self::rational(intrinsics, [k[0], k[1], k[2], 0.0, 0.0, 0.0], p, 0.0)
    }

    /// A checked camera with the rational model's `k = [k1, .., k6]`, `p = [p1, p2]` and a
    /// radius bound `rpmax` (0: none).
    pub fn rational(
        intrinsics: Intrinsics,
        k: [f64; 6],
        p: [f64; 2],
        rpmax: f64,
    ) -> Result<Self, Invalid> {
        checked(Self::unchecked(intrinsics, k, p, rpmax), Self::validate)
    }

    /// The camera without the checks; computes `r_max` and the field of view.
    pub(crate) fn unchecked(intrinsics: Intrinsics, k: [f64; 6], p: [f64; 2], rpmax: f64) -> Self {
        let mut cam = PinholeRadTan {
            intrinsics,
            k: [k[0], k[1], k[2]],
            p,
            k_den: [k[3], k[4], k[5]],
            rpmax,
            distortion: RadTan::new(k, p, rpmax),
            fov: 0.0,
        };
        let Intrinsics { cx, cy, width, .. } = intrinsics;
        let edges = [-0.5, width as f64 - 0.5].map(|u| cam.edge_ray(cx, u, cy));
        cam.fov = match edges {
            [Some(l), Some(r)] => {
                let dot = l[0] * r[0] + l[1] * r[1] + l[2] * r[2];
                let cross = [
                    l[1] * r[2] - l[2] * r[1],
                    l[2] * r[0] - l[0] * r[2],
                    l[0] * r[1] - l[1] * r[0],
                ];
                cross[0].hypot(cross[1]).hypot(cross[2]).atan2(dot)
            }
            _ => 0.0, // only for invalid cameras (non-finite values), which `validate` refuses
        };
        cam
    }

    /// The ray of the image edge `(u, v)`, or where it lies past the fold, of the last point on
    /// the row from `(cx, v)` towards it that unprojects.
    fn edge_ray(&self, cx: f64, u: f64, v: f64) -> Option<[f64; 3]> {
        if let Some(ray) = self.unproject([u, v]) {
            return Some(ray);
        }
        let at = |t: f64| self.unproject([cx + t * (u - cx), v]);
        let ok = |t: f64| at(t).is_some();
        let grid = (1..=EDGE_SCAN_STEPS).map(|i| i as f64 / EDGE_SCAN_STEPS as f64);
        at(last_ok(ok, 0.0, grid)?)
    }

    /// Every float finite, the intrinsics ([`Intrinsics::validate`]), `rpmax >= 0`; the error
    /// names the field. A distortion that folds inside the image is valid (module docs).
    pub fn validate(&self) -> Checked {
        check_finite(self.fields())?;
        self.intrinsics.validate()?;
        check_rule("rpmax", self.rpmax, self.rpmax >= 0.0, ">= 0 (0: no bound)")?;
        if self.unproject([self.cx, self.cy]).is_none() {
            return Err(Invalid::new(
                "k4, k5, k6",
                "the distortion has no inverse at the principal point".to_string(),
            ));
        }
        Ok(())
    }

    /// End of the invertible radial range on the `z = 1` plane: the first `r > 0` where the
    /// radial part `r R(r^2)` stops increasing or its denominator vanishes, bounded by `rpmax`
    /// when that is > 0; infinity if none below `r^2 = 1e12`.
    pub fn r_max(&self) -> f64 {
        self.distortion.r_max
    }

    /// `(x'', y'')` of a normalised point `(x', y')` (module docs).
    pub fn distort(&self, m: [f64; 2]) -> [f64; 2] {
        self.distortion.distort(m)
    }

    /// The Jacobian `d(x'', y'') / d(x', y')`, row-major (see the `radtan` module).
    pub fn distort_jacobian(&self, m: [f64; 2]) -> [[f64; 2]; 2] {
        self.distortion.jacobian(m)
    }

    /// Solves `distort(m) = target` (see the `radtan` module). Returns `(m, iterations)`, or
    /// `None` where no point of the domain has a residual below its tolerance.
    pub(crate) fn undistort(&self, target: [f64; 2]) -> Option<([f64; 2], usize)> {
        self.distortion.undistort(target)
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None`: `diag(fx, fy) D [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]` with `D` the
    /// distortion Jacobian ([`PinholeRadTan::distort_jacobian`]).
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        let d = self.distort_jacobian([x / z, y / z]);
        let n = [[1.0 / z, 0.0, -x / (z * z)], [0.0, 1.0 / z, -y / (z * z)]];
        let f = [self.fx, self.fy];
        Some([0, 1].map(|r| [0, 1, 2].map(|c| f[r] * (d[r][0] * n[0][c] + d[r][1] * n[1][c]))))
    }
}

impl CameraModel for PinholeRadTan {
    /// The OpenCV distortion (module docs), or `None` for `z <= 0`, a non-finite ray, or a point
    /// outside the invertible domain (`r > r_max` or a folded Jacobian).
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        let [x, y, z] = ray;
        if !finite3(ray) || z <= 0.0 {
            return None;
        }
        let m = [x / z, y / z];
        if !self.distortion.in_domain(m) {
            return None;
        }
        let [xd, yd] = self.distort(m);
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// The unit ray along `[x', y', 1]` with `(x', y')` the undistorted point (Newton with a
    /// residual check, see the `radtan` module); `None` past the fold.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let target = [(px[0] - self.cx) / self.fx, (px[1] - self.cy) / self.fy];
        let (m, _) = self.undistort(target)?;
        normalize([m[0], m[1], 1.0])
    }

    fn size(&self) -> [usize; 2] {
        self.intrinsics.size()
    }

    /// The angle between the rays of the left and right image edges on the principal row
    /// (computed by [`PinholeRadTan::new`]).
    fn fov(&self) -> f64 {
        self.fov
    }

    /// The intrinsics rescaled ([`Intrinsics::rescaled`]); the coefficients unchanged (they act
    /// on the `z = 1` plane); `r_max` and the field of view recomputed.
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        let intrinsics = self.intrinsics.rescaled(scale, convention);
        let [k1, k2, k3] = self.k;
        let [k4, k5, k6] = self.k_den;
        let k = [k1, k2, k3, k4, k5, k6];
        Camera::PinholeRadTan(PinholeRadTan::unchecked(intrinsics, k, self.p, self.rpmax))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::{assert_newton_on_every_pixel, euroc, radtan};

    /// Newton to |step| < 1e-12 with quadratic convergence leaves round-off, ~1e-16 of the
    /// normalised coordinates (~1e-13 px); 1e-9 px is margin.
    const PX_TOL: f64 = 1e-9;
    /// A bisected root or a sum of two atans: a few ulps; 1e-12 is margin.
    const ROUND_OFF_TOL: f64 = 1e-12;

    #[test]
    fn r_max_is_the_fold_of_the_radial_part() {
        // 1 + 3 k1 s + 5 k2 s^2 with k1 = -0.2834, k2 = 0.07396: discriminant
        // 9 k1^2 - 20 k2 = 0.7229 - 1.4792 < 0, so it never vanishes: unbounded.
        assert_eq!(euroc().r_max(), f64::INFINITY);
        // k1 = -0.5 alone: 1 - 1.5 r^2 = 0 at r = sqrt(2/3).
        let c = radtan(
            500.0,
            500.0,
            320.0,
            240.0,
            [-0.5, 0.0, 0.0],
            [0.0; 2],
            640,
            480,
        );
        assert!(
            (c.r_max() - (2.0f64 / 3.0).sqrt()).abs() < ROUND_OFF_TOL,
            "{}",
            c.r_max()
        );
        let inside = c.r_max() * 0.999;
        let outside = c.r_max() * 1.001;
        assert!(c.project([inside, 0.0, 1.0]).is_some());
        assert_eq!(c.project([outside, 0.0, 1.0]), None);
        // The image of the fold and beyond has no inverse in the domain.
        let edge = c.fx * c.distort([c.r_max(), 0.0])[0];
        assert_eq!(c.unproject([c.cx + edge * 1.01, c.cy]), None);
        assert!(c.unproject([c.cx + edge * 0.99, c.cy]).is_some());
    }

    #[test]
    fn newton_converges_on_every_euroc_pixel() {
        let c = euroc();
        // The error in pixels.
        let solve = |target: [f64; 2]| {
            let (m, iters) = c.undistort(target).expect("converges");
            let back = c.distort(m);
            let err = (c.fx * (back[0] - target[0])).hypot(c.fy * (back[1] - target[1]));
            (iters, err)
        };
        assert_newton_on_every_pixel(&c, solve, [8, 6], PX_TOL);
    }

    /// A distortion that folds inside the image (k1 = -0.5 on a wide sensor, and a rational
    /// camera like COLMAP FULL_OPENCV fits with a fold before the corners) is a valid camera:
    /// pixels past the fold are `None`, every other pixel round-trips, and the field of view
    /// ends at the fold.
    #[test]
    fn a_fold_inside_the_image_is_the_domain_edge() {
        let intrinsics = Intrinsics::from_parts([300.0, 300.0, 320.0, 240.0], [640, 480]);
        for (k, p) in [
            ([-0.5, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0]),
            ([0.2, -0.1, 0.0, 0.6, 0.0, 0.0], [0.003, -0.002]),
        ] {
            let c = PinholeRadTan::rational(intrinsics, k, p, 0.0).expect("a folding camera");
            let (mut inside, mut outside) = (0, 0);
            for v in (0..480).step_by(7) {
                for u in (0..640).step_by(7) {
                    let px = [u as f64, v as f64];
                    let Some(ray) = c.unproject(px) else {
                        outside += 1;
                        continue;
                    };
                    inside += 1;
                    let back = c.project(ray).expect("inside the domain");
                    let err = (back[0] - px[0]).hypot(back[1] - px[1]);
                    assert!(err < PX_TOL, "{k:?} {px:?}: {err} px");
                }
            }
            assert!(inside > 0 && outside > 0, "{k:?}: {inside} {outside}");
            // The field of view is that of the last pixels that unproject on the principal row:
            // with p = 0 and a centred principal point, the fold's radius either side.
            let half = c.fx * c.distort([c.r_max(), 0.0])[0];
            assert!(half < 320.0, "{half}");
            if p == [0.0, 0.0] {
                let want = 2.0 * c.r_max().atan();
                assert!((c.fov() - want).abs() < 1e-6, "{} vs {want}", c.fov());
            }
        }
    }

    #[test]
    fn zero_distortion_is_the_pinhole() {
        // cx = (width - 1) / 2: the pinhole's fov formula is exact for a centred principal point.
        let c = radtan(540.0, 530.0, 539.5, 480.0, [0.0; 3], [0.0; 2], 1080, 960);
        let pin = crate::camera::Pinhole::new(Intrinsics {
            fx: 540.0,
            fy: 530.0,
            cx: 539.5,
            cy: 480.0,
            width: 1080,
            height: 960,
        })
        .unwrap();
        for ray in [[0.3, -0.2, 1.0], [2.0, 1.0, 0.5], [-1e-3, 4.0, 0.1]] {
            assert_eq!(c.project(ray), pin.project(ray));
        }
        assert!((c.fov() - pin.fov()).abs() < ROUND_OFF_TOL);
        assert_eq!(c.project([0.3, 0.1, 0.0]), None);
    }
}
