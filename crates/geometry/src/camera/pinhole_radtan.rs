//! The pinhole camera with radial-tangential ("plumb bob", Brown-Conrady) distortion, in OpenCV's
//! 5-parameter form `k1, k2, p1, p2, k3` (OpenCV `calib3d` documentation, "Detailed
//! description"; Kalibr's `pinhole-radtan` with `k3 = 0`; COLMAP's `OPENCV`).
//!
//! Projection of a ray `[x, y, z]` with `z > 0` (camera frame: x right, y down, z forward):
//!
//! ```text
//! x' = x / z,  y' = y / z,  r^2 = x'^2 + y'^2
//! radial = 1 + k1 r^2 + k2 r^4 + k3 r^6
//! x'' = x' radial + 2 p1 x' y' + p2 (r^2 + 2 x'^2)
//! y'' = y' radial + p1 (r^2 + 2 y'^2) + 2 p2 x' y'
//! u = fx x'' + cx,   v = fy y'' + cy
//! ```
//!
//! The distortion is only invertible where it does not fold. Its domain here is
//! `r <= r_max`, where `r_max` is the first radius at which the radial part `r radial(r)` stops
//! increasing (`1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6 <= 0`, infinite if it never does), and where
//! the determinant of the 2x2 Jacobian `d(x'', y'') / d(x', y')` is positive.
//!
//! Unprojection solves `distort(x', y') = (x'', y'')` by Newton's method on the 2x2 system from
//! `(x'', y'')` (OpenCV's `undistortPoints` uses a fixed-point iteration instead), halving any step
//! that would leave the domain or not reduce the residual; converged when the step is below
//! `EPS` within `MAX_ITER` iterations, else `None`.
//!
//! The field of view is derived: the angle between the rays of the left and right image edges
//! (`u = -0.5` and `u = width - 0.5`) on the principal row. Pixels are `[u, v]` = (column, row),
//! top-left pixel centre at `(0, 0)`; radians.

use super::intrinsics::deref_intrinsics;
use super::schema::{check_finite, checked, raw_camera_file, CameraFile, Checked, Invalid};
use super::solve::last_ok;
use super::{Camera, CameraModel, Intrinsics, PixelConvention};
use crate::vec3::{finite3, normalize};

/// Newton iterations allowed when undistorting. Newton converges quadratically from `(x'', y'')`
/// in 3 to 6 steps for realistic lenses (measured on the test cameras); halved steps near the
/// domain edge converge linearly, and 100 leaves room for that.
pub const MAX_ITER: usize = 100;

/// Convergence threshold on the Newton step, in normalised image units (`x/z`): `fx * EPS` is
/// ~5e-10 px for `fx ~ 500`, and it stays above the ~1e-16 round-off of the coordinates, so the
/// test can fire.
pub const EPS: f64 = 1e-12;

/// Grid points on `log10(r^2) in [-6, 12]` scanned for the first fold of the radial part; the
/// polynomial `1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3` in `s = r^2` has at most three roots, so a
/// sign change narrower than one grid step (2.1 %) would take a near-double root.
const SCAN_STEPS: usize = 2000;

/// Beyond `r^2 = 1e12` (89.99994 deg off-axis) the radial range is treated as unbounded.
const SCAN_MAX_LOG10_R2: f64 = 12.0;

/// Below `r^2 = 1e-6` the radial derivative is `1 + O(1e-6 k1)`: positive for any real lens.
const SCAN_MIN_LOG10_R2: f64 = -6.0;

/// Pixels checked along each edge of the image for invertibility (plus the corners): a fold
/// narrower than 1/256 of an edge between two checked pixels is not realistic.
const BORDER_SAMPLES: usize = 256;

/// A pinhole camera with OpenCV radial-tangential distortion.
///
/// Build it with [`PinholeRadTan::new`], which finds the radial range `r_max` and the field of
/// view. Equality compares the public fields only (the derived values are functions of them).
#[derive(Clone, Debug)]
pub struct PinholeRadTan {
    intrinsics: Intrinsics,
    /// Radial coefficients `[k1, k2, k3]` (of `r^2`, `r^4`, `r^6`).
    pub k: [f64; 3],
    /// Tangential coefficients `[p1, p2]`.
    pub p: [f64; 2],
    /// End of the monotonic radial range on the `z = 1` plane (may be infinite).
    r_max: f64,
    /// Edge-to-edge horizontal field of view, radians.
    fov: f64,
}

deref_intrinsics!(PinholeRadTan);

impl PartialEq for PinholeRadTan {
    fn eq(&self, other: &Self) -> bool {
        self.intrinsics == other.intrinsics && self.k == other.k && self.p == other.p
    }
}

raw_camera_file! {
    /// A pinhole camera with OpenCV radial-tangential distortion, as written.
    pinhole struct Raw {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
    }
}

impl CameraFile for PinholeRadTan {
    const MODEL: &'static str = "pinhole-radtan";
    type Raw = Raw;
    fn fields(&self) -> Vec<(&'static str, f64)> {
        let ([k1, k2, k3], [p1, p2]) = (self.k, self.p);
        let mut fields = self.intrinsics.fields().to_vec();
        fields.extend([("k1", k1), ("k2", k2), ("p1", p1), ("p2", p2), ("k3", k3)]);
        fields
    }
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        PinholeRadTan::new(r.intrinsics(), [r.k1, r.k2, r.k3], [r.p1, r.p2])
    }
}

impl PinholeRadTan {
    /// A checked camera (see [`PinholeRadTan::validate`]) with `k = [k1, k2, k3]`,
    /// `p = [p1, p2]`; computes `r_max` and the field of view.
    pub fn new(intrinsics: Intrinsics, k: [f64; 3], p: [f64; 2]) -> Result<Self, Invalid> {
        checked(Self::unchecked(intrinsics, k, p), Self::validate)
    }

    /// The camera without the checks; computes `r_max` and the field of view. If an image edge
    /// does not unproject (the distortion folds inside the image, which [`PinholeRadTan::new`]
    /// rejects) the field of view falls back to the undistorted pinhole's
    /// `2 atan(width / (2 fx))`.
    pub(crate) fn unchecked(intrinsics: Intrinsics, k: [f64; 3], p: [f64; 2]) -> Self {
        let mut cam = PinholeRadTan {
            intrinsics,
            k,
            p,
            r_max: 0.0,
            fov: 0.0,
        };
        let Intrinsics { fx, cy, width, .. } = intrinsics;
        cam.r_max = cam.find_r_max();
        let edges = [-0.5, width as f64 - 0.5].map(|u| cam.unproject([u, cy]));
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
            _ => 2.0 * (width as f64 / (2.0 * fx)).atan(),
        };
        cam
    }

    /// Every float finite, the intrinsics ([`Intrinsics::validate`]), and every pixel of the
    /// image border unprojects (the distortion does not fold inside the image); the error names
    /// the field.
    pub fn validate(&self) -> Checked {
        check_finite(self.fields())?;
        self.intrinsics.validate()?;
        // The outer pixel edges, BORDER_SAMPLES + 1 points per side (corners included).
        let (w, h) = (self.width as f64, self.height as f64);
        let border = (0..=BORDER_SAMPLES).flat_map(|i| {
            let t = i as f64 / BORDER_SAMPLES as f64;
            let (u, v) = (-0.5 + t * w, -0.5 + t * h);
            [[u, -0.5], [u, h - 0.5], [-0.5, v], [w - 0.5, v]]
        });
        for px in border {
            if self.unproject(px).is_none() {
                return Err(Invalid::new(
                    "k1, k2, p1, p2, k3",
                    format!(
                        "the distortion folds inside the image: pixel ({}, {}) has no inverse \
                         (the radial part stops increasing at r = {:.4} on the z = 1 plane)",
                        px[0],
                        px[1],
                        self.r_max()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// End of the monotonic radial range on the `z = 1` plane: the first `r > 0` where
    /// `1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6 <= 0`, or infinity if none below `r^2 = 1e12`.
    pub fn r_max(&self) -> f64 {
        self.r_max
    }

    fn radial_derivative(&self, s: f64) -> f64 {
        let [k1, k2, k3] = self.k;
        1.0 + s * (3.0 * k1 + s * (5.0 * k2 + s * 7.0 * k3))
    }

    /// Scans `s = r^2` on a log grid for the first non-positive radial derivative, then bisects.
    fn find_r_max(&self) -> f64 {
        let ok = |s: f64| self.radial_derivative(s) > 0.0;
        let s_at = |i: usize| {
            let t = i as f64 / SCAN_STEPS as f64;
            10f64.powf(SCAN_MIN_LOG10_R2 + t * (SCAN_MAX_LOG10_R2 - SCAN_MIN_LOG10_R2))
        };
        if !ok(0.0) {
            return 0.0; // only with non-finite coefficients
        }
        last_ok(ok, 0.0, (0..=SCAN_STEPS).map(s_at)).map_or(f64::INFINITY, f64::sqrt)
    }

    /// `(x'', y'')` of a normalised point `(x', y')` (module docs).
    pub fn distort(&self, m: [f64; 2]) -> [f64; 2] {
        let [x, y] = m;
        let [k1, k2, k3] = self.k;
        let [p1, p2] = self.p;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        [
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        ]
    }

    /// The Jacobian `d(x'', y'') / d(x', y')`, row-major:
    ///
    /// ```text
    /// dradial/dx' = 2 x' (k1 + 2 k2 r^2 + 3 k3 r^4)        (likewise for y')
    /// dx''/dx' = radial + x' dradial/dx' + 2 p1 y' + 6 p2 x'
    /// dx''/dy' = x' dradial/dy' + 2 p1 x' + 2 p2 y'
    /// dy''/dx' = y' dradial/dx' + 2 p1 x' + 2 p2 y'
    /// dy''/dy' = radial + y' dradial/dy' + 6 p1 y' + 2 p2 x'
    /// ```
    pub fn distort_jacobian(&self, m: [f64; 2]) -> [[f64; 2]; 2] {
        let [x, y] = m;
        let [k1, k2, k3] = self.k;
        let [p1, p2] = self.p;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let g = 2.0 * (k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3));
        let (drx, dry) = (g * x, g * y);
        [
            [
                radial + x * drx + 2.0 * p1 * y + 6.0 * p2 * x,
                x * dry + 2.0 * p1 * x + 2.0 * p2 * y,
            ],
            [
                y * drx + 2.0 * p1 * x + 2.0 * p2 * y,
                radial + y * dry + 6.0 * p1 * y + 2.0 * p2 * x,
            ],
        ]
    }

    /// Whether a normalised point lies in the invertible domain (`r <= r_max`, `det J > 0`).
    fn in_domain(&self, m: [f64; 2]) -> bool {
        let j = self.distort_jacobian(m);
        m[0].hypot(m[1]) <= self.r_max && j[0][0] * j[1][1] - j[0][1] * j[1][0] > 0.0
    }

    /// Solves `distort(m) = target` by damped Newton (module docs). Returns `(m, iterations)`,
    /// or `None` without convergence in `MAX_ITER` steps.
    pub(crate) fn undistort(&self, target: [f64; 2]) -> Option<([f64; 2], usize)> {
        if !(target[0].is_finite() && target[1].is_finite()) {
            return None;
        }
        let residual = |m: [f64; 2]| {
            let d = self.distort(m);
            [d[0] - target[0], d[1] - target[1]]
        };
        let norm = |v: [f64; 2]| v[0].hypot(v[1]);
        let mut m = target;
        if !self.in_domain(m) {
            m = [0.0, 0.0];
        }
        let mut f = residual(m);
        for iter in 1..=MAX_ITER {
            if f == [0.0, 0.0] {
                return Some((m, iter));
            }
            let j = self.distort_jacobian(m);
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            // Newton step: -J^-1 f.
            let mut step = [
                -(j[1][1] * f[0] - j[0][1] * f[1]) / det,
                -(-j[1][0] * f[0] + j[0][0] * f[1]) / det,
            ];
            if !(step[0].is_finite() && step[1].is_finite()) {
                return None;
            }
            // Halve until the step stays in the domain and does not increase the residual (a
            // full step that lands on the root exactly is always accepted).
            let mut next = [m[0] + step[0], m[1] + step[1]];
            let mut f_next = residual(next);
            let mut halvings = 0;
            while !(self.in_domain(next) && norm(f_next) <= norm(f)) && halvings < 60 {
                step = [0.5 * step[0], 0.5 * step[1]];
                next = [m[0] + step[0], m[1] + step[1]];
                f_next = residual(next);
                halvings += 1;
            }
            m = next;
            f = f_next;
            if norm(step) < EPS {
                return Some((m, iter));
            }
        }
        None
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
        if !self.in_domain(m) {
            return None;
        }
        let [xd, yd] = self.distort(m);
        Some([self.fx * xd + self.cx, self.fy * yd + self.cy])
    }

    /// The unit ray along `[x', y', 1]` with `(x', y')` the undistorted point (Newton, see
    /// `MAX_ITER`, `EPS`); `None` without convergence or outside the domain.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let target = [(px[0] - self.cx) / self.fx, (px[1] - self.cy) / self.fy];
        let (m, _) = self.undistort(target)?;
        if !self.in_domain(m) {
            return None;
        }
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

    /// The intrinsics rescaled ([`Intrinsics::rescaled`]); `k`, `p` unchanged (they act on the
    /// `z = 1` plane); `r_max` and the field of view recomputed.
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        let intrinsics = self.intrinsics.rescaled(scale, convention);
        Camera::PinholeRadTan(PinholeRadTan::unchecked(intrinsics, self.k, self.p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::{euroc, radtan};

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
        let (mut worst, mut worst_err) = (0, 0.0f64);
        for v in 0..c.height {
            for u in 0..c.width {
                let target = [(u as f64 - c.cx) / c.fx, (v as f64 - c.cy) / c.fy];
                let (m, iters) = c.undistort(target).expect("converges");
                worst = worst.max(iters);
                let back = c.distort(m);
                let err = (c.fx * (back[0] - target[0])).hypot(c.fy * (back[1] - target[1]));
                worst_err = worst_err.max(err);
            }
        }
        assert!(
            worst <= 8,
            "Newton took {worst} steps (measured: 6 at most)"
        );
        assert!(worst_err < PX_TOL, "{worst_err} px");
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
