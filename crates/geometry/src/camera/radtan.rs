//! The radial-tangential ("plumb bob", Brown-Conrady) distortion of a normalised image point,
//! with OpenCV's rational radial factor, shared by the models that apply it: the pinhole
//! ([`super::PinholeRadTan`]) and Mei's unified model ([`super::Mei`]).
//!
//! OpenCV `calib3d` documentation ("Detailed description"), Basalt `pinhole-radtan8`, COLMAP
//! `FULL_OPENCV`, Kalibr `radtan` (`k3..k6 = 0`), with `(x', y')` the undistorted point:
//!
//! ```text
//! s = r^2 = x'^2 + y'^2
//! R(s) = (1 + k1 s + k2 s^2 + k3 s^3) / (1 + k4 s + k5 s^2 + k6 s^3)
//! x'' = x' R + 2 p1 x' y' + p2 (s + 2 x'^2)
//! y'' = y' R + p1 (s + 2 y'^2) + 2 p2 x' y'
//! ```
//!
//! The distortion is only invertible where it does not fold. Its domain is `r <= r_max` and a
//! positive determinant of the 2x2 Jacobian `d(x'', y'') / d(x', y')`, where `r_max` is the
//! first radius at which the radial part `r R(r^2)` stops increasing (`R + 2 s R'(s) <= 0`) or
//! the denominator reaches 0 (infinite if neither happens), further limited by a source's own
//! bound (Basalt's `rpmax`) where it gives one. Points past the fold are outside the model.
//!
//! [`RadTan::undistort`] solves `distort(m) = target` by Newton's method on the 2x2 system from
//! `target` (OpenCV's `undistortPoints` uses a fixed-point iteration instead), halving any step
//! that would leave the domain or not reduce the residual. It answers only when the residual
//! itself is below [`RESIDUAL_TOL`]: a stalled iteration (tiny halved steps far from the root,
//! as happens next to the fold) is `None`, never a wrong point.

use super::solve::last_ok;

/// Newton iterations allowed when undistorting. Newton converges quadratically from the target
/// in 3 to 6 steps for realistic lenses (measured on the test cameras); halved steps near the
/// domain edge converge linearly, and 100 leaves room for that.
pub const MAX_ITER: usize = 100;

/// Convergence threshold on the Newton step, in normalised image units (`x/z`): `fx * EPS` is
/// ~5e-10 px for `fx ~ 500`, and it stays above the ~1e-16 round-off of the coordinates, so the
/// test can fire.
pub const EPS: f64 = 1e-12;

/// The largest residual `|distort(m) - target|` (normalised units) an undistorted point may
/// leave: times a focal length up to 1e4 px it is 1e-6 px, the accuracy the imports are checked
/// to; a converged Newton leaves ~1e-15.
pub const RESIDUAL_TOL: f64 = 1e-10;

/// Grid points on `log10(r^2) in [-6, 12]` scanned for the first fold of the radial part: a
/// sign change narrower than one grid step (2.1 %) would take a near-double root.
const SCAN_STEPS: usize = 2000;

/// Beyond `r^2 = 1e12` (89.99994 deg off-axis) the radial range is treated as unbounded.
const SCAN_MAX_LOG10_R2: f64 = 12.0;

/// Below `r^2 = 1e-6` the radial derivative is `1 + O(1e-6 k)`: positive for any real lens.
const SCAN_MIN_LOG10_R2: f64 = -6.0;

/// Radial-tangential distortion with rational radial factor; build with [`RadTan::new`], which
/// finds the domain's radius `r_max`.
#[derive(Clone, Debug)]
pub(crate) struct RadTan {
    /// `[k1, k2, k3, k4, k5, k6]`: numerator `k1..k3`, denominator `k4..k6`.
    pub k: [f64; 6],
    /// `[p1, p2]`.
    pub p: [f64; 2],
    /// End of the monotonic radial range (or the source's bound), may be infinite.
    pub r_max: f64,
    /// No point of the domain distorts farther than this from the centre (see
    /// [`RadTan::new`]); infinite with `r_max`.
    rd_bound: f64,
}

impl RadTan {
    /// The distortion with its domain: the radial fold, limited to `bound` when `bound > 0`
    /// (Basalt's `rpmax`; 0 means none).
    pub fn new(k: [f64; 6], p: [f64; 2], bound: f64) -> Self {
        let mut d = RadTan {
            k,
            p,
            r_max: 0.0,
            rd_bound: f64::INFINITY,
        };
        d.r_max = d.find_r_max();
        if bound > 0.0 {
            d.r_max = d.r_max.min(bound);
        }
        // The radial part r R(r^2) increases up to r_max, and the tangential part is at most
        // 3 (|p1| + |p2|) r^2 long: a target beyond their sum at r_max (plus round-off) has no
        // preimage in the domain, so `undistort` refuses it without iterating (past a fold, a
        // damped Newton would otherwise halve its way through every iteration first).
        if d.r_max.is_finite() {
            let (s, [p1, p2]) = (d.r_max * d.r_max, d.p);
            let (radial, _, _) = d.radial(s);
            let reach = d.r_max * radial.abs() + 3.0 * (p1.abs() + p2.abs()) * s;
            d.rd_bound = reach * (1.0 + 1e-9) + 1e-12;
        }
        d
    }

    /// `(R(s), R'(s))` with `R = N / D` (module docs); the denominator `D` too.
    fn radial(&self, s: f64) -> (f64, f64, f64) {
        let [k1, k2, k3, k4, k5, k6] = self.k;
        let n = 1.0 + s * (k1 + s * (k2 + s * k3));
        let dn = k1 + s * (2.0 * k2 + s * 3.0 * k3);
        let d = 1.0 + s * (k4 + s * (k5 + s * k6));
        let dd = k4 + s * (2.0 * k5 + s * 3.0 * k6);
        (n / d, (dn * d - n * dd) / (d * d), d)
    }

    /// Scans `s = r^2` on a log grid for the first point where `d(r R)/dr = R + 2 s R'` or the
    /// denominator is not positive, then bisects.
    fn find_r_max(&self) -> f64 {
        let ok = |s: f64| {
            let (r, dr, den) = self.radial(s);
            den > 0.0 && r + 2.0 * s * dr > 0.0
        };
        let s_at = |i: usize| {
            let t = i as f64 / SCAN_STEPS as f64;
            10f64.powf(SCAN_MIN_LOG10_R2 + t * (SCAN_MAX_LOG10_R2 - SCAN_MIN_LOG10_R2))
        };
        if !ok(0.0) {
            return 0.0; // only with non-finite coefficients
        }
        last_ok(ok, 0.0, (0..=SCAN_STEPS).map(s_at)).map_or(f64::INFINITY, f64::sqrt)
    }

    /// The distorted point of `m = (x', y')` (module docs).
    pub fn distort(&self, m: [f64; 2]) -> [f64; 2] {
        let [x, y] = m;
        let [p1, p2] = self.p;
        let s = x * x + y * y;
        let (r, _, _) = self.radial(s);
        [
            x * r + 2.0 * p1 * x * y + p2 * (s + 2.0 * x * x),
            y * r + p1 * (s + 2.0 * y * y) + 2.0 * p2 * x * y,
        ]
    }

    /// The Jacobian `d(x'', y'') / d(x', y')`, row-major:
    ///
    /// ```text
    /// dR/dx' = 2 x' R'(s)        (likewise for y')
    /// dx''/dx' = R + x' dR/dx' + 2 p1 y' + 6 p2 x'
    /// dx''/dy' = x' dR/dy' + 2 p1 x' + 2 p2 y'
    /// dy''/dx' = y' dR/dx' + 2 p1 x' + 2 p2 y'
    /// dy''/dy' = R + y' dR/dy' + 6 p1 y' + 2 p2 x'
    /// ```
    pub fn jacobian(&self, m: [f64; 2]) -> [[f64; 2]; 2] {
        let [x, y] = m;
        let [p1, p2] = self.p;
        let (r, dr, _) = self.radial(x * x + y * y);
        let (drx, dry) = (2.0 * dr * x, 2.0 * dr * y);
        [
            [
                r + x * drx + 2.0 * p1 * y + 6.0 * p2 * x,
                x * dry + 2.0 * p1 * x + 2.0 * p2 * y,
            ],
            [
                y * drx + 2.0 * p1 * x + 2.0 * p2 * y,
                r + y * dry + 6.0 * p1 * y + 2.0 * p2 * x,
            ],
        ]
    }

    /// Whether an undistorted point lies in the invertible domain (`r <= r_max`, `det J > 0`).
    pub fn in_domain(&self, m: [f64; 2]) -> bool {
        let j = self.jacobian(m);
        m[0].hypot(m[1]) <= self.r_max && j[0][0] * j[1][1] - j[0][1] * j[1][0] > 0.0
    }

    /// Solves `distort(m) = target` for `m` in the domain by damped Newton (module docs).
    /// Returns `(m, iterations)`, or `None` when the residual does not fall below
    /// [`RESIDUAL_TOL`] in [`MAX_ITER`] steps or the iteration stalls first.
    pub fn undistort(&self, target: [f64; 2]) -> Option<([f64; 2], usize)> {
        if !(target[0].is_finite() && target[1].is_finite()) {
            return None;
        }
        if target[0].hypot(target[1]) > self.rd_bound {
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
            let j = self.jacobian(m);
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
            if !self.in_domain(next) {
                return None;
            }
            m = next;
            f = f_next;
            if norm(step) < EPS {
                // A small step is convergence only where the residual is small too; a small
                // halved step far from the root is a stall.
                return (norm(f) <= RESIDUAL_TOL).then_some((m, iter));
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::tests::assert_matches_central_differences;

    /// A bisected root: a few ulps; 1e-12 is margin.
    const ROUND_OFF_TOL: f64 = 1e-12;

    #[test]
    fn rational_factor_and_its_fold() {
        // k4 = 0.5 alone: R = 1 / (1 + s / 2), r R = r / (1 + r^2 / 2) peaks at r = sqrt(2).
        let d = RadTan::new([0.0, 0.0, 0.0, 0.5, 0.0, 0.0], [0.0; 2], 0.0);
        assert!((d.r_max - 2f64.sqrt()).abs() < ROUND_OFF_TOL, "{}", d.r_max);
        // A bound closer in wins.
        let b = RadTan::new([0.0, 0.0, 0.0, 0.5, 0.0, 0.0], [0.0; 2], 0.8);
        assert_eq!(b.r_max, 0.8);
        assert!(!b.in_domain([0.81, 0.0]) && b.in_domain([0.79, 0.0]));
        // A denominator that reaches zero: 1 - s = 0 at r = 1, before r R = r / (1 - r^2) folds.
        let pole = RadTan::new([0.0, 0.0, 0.0, -1.0, 0.0, 0.0], [0.0; 2], 0.0);
        assert!((pole.r_max - 1.0).abs() < ROUND_OFF_TOL, "{}", pole.r_max);
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let d = RadTan::new([-0.3, 0.1, -0.02, 0.05, 0.01, -0.003], [0.004, -0.002], 0.0);
        let h = 1e-6;
        for m in [[0.1, -0.2], [0.5, 0.3], [-0.7, 0.05]] {
            let j = d.jacobian(m);
            // Truncation ~h^2 |f'''| ~ 1e-12, cancellation ~1e-16 / 1e-6 = 1e-10.
            assert_matches_central_differences(|x| d.distort(x), m, h, &j, 1e-8, &format!("{m:?}"));
        }
    }

    /// The regression the residual check fixes: past the image of the fold the damped Newton
    /// halves its steps to nothing far from any root; that must be `None`, not the stalled point.
    #[test]
    fn a_stalled_newton_is_none_not_a_wrong_point() {
        let d = RadTan::new([-0.5, 0.0, 0.0, 0.0, 0.0, 0.0], [0.002, -0.001], 0.0);
        let edge = d.distort([d.r_max, 0.0])[0];
        // Just past the fold (within the quick reach bound, so Newton runs) and far past it.
        for scale in [1.001, 1.005, 1.5, 3.0] {
            assert_eq!(d.undistort([edge * scale, 0.01]), None, "{scale}");
        }
        // Targets where the halved steps stalled next to the fold: without the residual check
        // these came back as points whose distortion misses them by 0.0025 to 0.0035
        // (~1.5 px at fx = 500).
        for target in [[-0.5487, -0.0302], [-0.5487, -0.0181], [-0.5487, -0.0060]] {
            assert_eq!(d.undistort(target), None, "{target:?}");
        }
        for scale in [0.2, 0.6, 0.9] {
            let (m, _) = d.undistort([edge * scale, 0.01]).unwrap();
            let back = d.distort(m);
            let err = (back[0] - edge * scale).hypot(back[1] - 0.01);
            assert!(err <= RESIDUAL_TOL, "{scale}: {err}");
        }
    }
}
