//! The one safeguarded 1-D solver of the camera models, and the scan that finds where a model
//! stops being invertible.
//!
//! [`increasing_root`] solves `g(x) = 0` for an increasing `g` on a bracket `[lo, hi]` by Newton's
//! method, `x <- x - g(x) / g'(x)`, keeping the bracket by the sign of `g` and taking a bisection
//! step whenever Newton would leave it (Numerical Recipes' `rtsafe`). Kannala-Brandt inverts
//! `d(theta) = r_d` with it, Scaramuzza `g(rho) = theta`.

/// Newton iterations allowed. Each failed Newton step falls back to a bisection step, and
/// bisection alone shrinks a bracket by 2^-50 in 50 steps; near a double root at the end of the
/// monotonic range Newton converges linearly (one bit per step), hence 100.
pub const MAX_ITER: usize = 100;

/// Solves `g(x) = 0` on `[lo, hi]` for `g` increasing there, from `x0` (clamped into the
/// bracket). `g_and_slope(x)` returns `(g(x), g'(x))`. Converged when `g(x) == 0` or the step is
/// below `eps` (in the units of `x`; each caller's `EPS` says why its value can fire). Returns
/// `(x, iterations)`, or `None` without convergence in [`MAX_ITER`] steps.
pub(crate) fn increasing_root(
    g_and_slope: impl Fn(f64) -> (f64, f64),
    [mut lo, mut hi]: [f64; 2],
    x0: f64,
    eps: f64,
) -> Option<(f64, usize)> {
    let mut x = x0.clamp(lo, hi);
    for iter in 1..=MAX_ITER {
        let (g, slope) = g_and_slope(x);
        if g == 0.0 {
            return Some((x, iter));
        }
        if g < 0.0 {
            lo = x;
        } else {
            hi = x;
        }
        let newton = x - g / slope;
        let next = if newton.is_finite() && newton >= lo && newton <= hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        let step = next - x;
        x = next;
        if step.abs() < eps {
            return Some((x, iter));
        }
    }
    None
}

/// Bisection steps refining a boundary once bracketed: 60 halvings take any bracket the scans
/// produce below one ulp, so the loop ends on the floating-point limit.
pub const REFINE_STEPS: usize = 60;

/// The last point where `ok` holds before it first fails along `points` (increasing, starting
/// where `ok` holds at `start`): bisects between the last good and the first failing point
/// ([`REFINE_STEPS`]). `None` if `ok` holds at every point.
pub(crate) fn last_ok(
    ok: impl Fn(f64) -> bool,
    start: f64,
    points: impl IntoIterator<Item = f64>,
) -> Option<f64> {
    let mut lo = start;
    for hi in points {
        if !ok(hi) {
            let mut hi = hi;
            for _ in 0..REFINE_STEPS {
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    break;
                }
                if ok(mid) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Some(lo);
        }
        lo = hi;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn newton_converges_quadratically_and_bisects_when_it_would_leave() {
        // x^3 - 2 on [0, 2]: Newton from 1 converges in a handful of steps.
        let cube = |x: f64| (x * x * x - 2.0, 3.0 * x * x);
        let (x, iters) = increasing_root(cube, [0.0, 2.0], 1.0, 1e-14).unwrap();
        assert!((x - 2f64.cbrt()).abs() < 1e-15, "{x}");
        assert!(iters < 10, "{iters}");
        // From 0 the slope vanishes: the first step bisects, then Newton takes over.
        let (x, iters) = increasing_root(cube, [0.0, 2.0], 0.0, 1e-14).unwrap();
        assert!((x - 2f64.cbrt()).abs() < 1e-15 && iters < 15, "{x} {iters}");
        // A tolerance the iteration cannot reach (no float squares to 2 exactly, and no step is
        // below 0): no convergence in MAX_ITER steps.
        let square = |x: f64| (x * x - 2.0, 2.0 * x);
        assert_eq!(increasing_root(square, [0.0, 2.0], 1.0, 0.0), None);
    }

    #[test]
    fn last_ok_refines_to_the_boundary() {
        let b = last_ok(|x| x < 0.3, 0.0, (1..=10).map(|i| i as f64 / 10.0)).unwrap();
        assert!(b < 0.3 && 0.3 - b < 1e-15, "{b}");
        assert_eq!(last_ok(|x| x < 5.0, 0.0, [1.0, 2.0]), None);
    }
}
