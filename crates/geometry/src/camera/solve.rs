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
/// below `eps` (in the units of `x`; each caller's `EPS` says why its value can fire) **and**
/// the residual there is small, `|g(x)| <= max_residual` (in the units of `g`): a small step
/// with a large residual (a bracket that shrank onto no root) is `None`, never a wrong root.
/// Returns `(x, iterations)`, or `None` without convergence in [`MAX_ITER`] steps.
pub(crate) fn increasing_root(
    g_and_slope: impl Fn(f64) -> (f64, f64),
    bracket: [f64; 2],
    x0: f64,
    [eps, max_residual]: [f64; 2],
) -> Option<(f64, usize)> {
    let [root] = increasing_roots(
        |_, x| g_and_slope(x),
        [bracket],
        [x0],
        [true],
        [eps, max_residual],
    );
    root
}

/// [`increasing_root`] for `L` equations at once, in lockstep: iteration `i` takes one step of
/// every lane still running, so that the CPU overlaps the lanes' independent chains of
/// dependent operations (a lone Newton iteration is one such chain). Each lane performs the
/// same operations as it would alone, so it gives the same bits. `g_and_slope(lane, x)`;
/// lanes with `solve[lane] == false` are skipped and return `None`.
pub(crate) fn increasing_roots<const L: usize>(
    g_and_slope: impl Fn(usize, f64) -> (f64, f64),
    brackets: [[f64; 2]; L],
    x0: [f64; L],
    mut solve: [bool; L],
    [eps, max_residual]: [f64; 2],
) -> [Option<(f64, usize)>; L] {
    let mut roots = [None; L];
    let [mut lo, mut hi] = [0, 1].map(|e| brackets.map(|b| b[e]));
    let mut x: [f64; L] = std::array::from_fn(|l| x0[l].clamp(lo[l], hi[l]));
    for iter in 1..=MAX_ITER {
        if !solve.contains(&true) {
            break;
        }
        for l in 0..L {
            if !solve[l] {
                continue;
            }
            let (g, slope) = g_and_slope(l, x[l]);
            if g == 0.0 {
                (roots[l], solve[l]) = (Some((x[l], iter)), false);
                continue;
            }
            if g < 0.0 {
                lo[l] = x[l];
            } else {
                hi[l] = x[l];
            }
            let newton = x[l] - g / slope;
            let next = if newton.is_finite() && newton >= lo[l] && newton <= hi[l] {
                newton
            } else {
                0.5 * (lo[l] + hi[l])
            };
            let step = next - x[l];
            x[l] = next;
            if step.abs() < eps {
                let (g_next, _) = g_and_slope(l, x[l]);
                let root = (g_next.abs() <= max_residual).then_some((x[l], iter));
                (roots[l], solve[l]) = (root, false);
            }
        }
    }
    roots
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
        let tol = [1e-14, 1e-12];
        let (x, iters) = increasing_root(cube, [0.0, 2.0], 1.0, tol).unwrap();
        assert!((x - 2f64.cbrt()).abs() < 1e-15, "{x}");
        assert!(iters < 10, "{iters}");
        // From 0 the slope vanishes: the first step bisects, then Newton takes over.
        let (x, iters) = increasing_root(cube, [0.0, 2.0], 0.0, tol).unwrap();
        assert!((x - 2f64.cbrt()).abs() < 1e-15 && iters < 15, "{x} {iters}");
        // A tolerance the iteration cannot reach (no float squares to 2 exactly, and no step is
        // below 0): no convergence in MAX_ITER steps.
        let square = |x: f64| (x * x - 2.0, 2.0 * x);
        assert_eq!(increasing_root(square, [0.0, 2.0], 1.0, [0.0, 1.0]), None);
    }

    #[test]
    fn a_bracket_without_a_root_is_none_not_its_end() {
        // x^3 + 1 > 0 on [0, 2]: the bracket shrinks onto 0, where the residual is 1.
        let shifted = |x: f64| (x * x * x + 1.0, 3.0 * x * x);
        assert_eq!(
            increasing_root(shifted, [0.0, 2.0], 1.0, [1e-14, 1e-9]),
            None
        );
    }

    #[test]
    fn last_ok_refines_to_the_boundary() {
        let b = last_ok(|x| x < 0.3, 0.0, (1..=10).map(|i| i as f64 / 10.0)).unwrap();
        assert!(b < 0.3 && 0.3 - b < 1e-15, "{b}");
        assert_eq!(last_ok(|x| x < 5.0, 0.0, [1.0, 2.0]), None);
    }
}
