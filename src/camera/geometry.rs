//! Small vector helpers shared by the camera models (plain `f64`, rays `[x, y, z]`).

/// Whether every component of `v` is finite.
pub(crate) fn finite3(v: [f64; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

/// `v / |v|`, or `None` for a zero or non-finite vector.
pub(crate) fn normalize(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = v[0].hypot(v[1]).hypot(v[2]);
    (n > 0.0 && n.is_finite() && finite3(v)).then(|| v.map(|c| c / n))
}

/// Angle in radians between the ray `v` (any length > 0) and the optical axis `+z`, in `[0, pi]`.
pub(crate) fn angle_to_axis(v: [f64; 3]) -> f64 {
    v[0].hypot(v[1]).atan2(v[2])
}

/// `w(alpha)` of the unified-model family (Usenko et al. 2018, Eq. 20): a ray projects iff
/// `z > -w d`, with `w = alpha / (1 - alpha)` for `alpha <= 0.5` (where the denominator
/// `alpha d + (1 - alpha) z` vanishes) and `w = (1 - alpha) / alpha` above (where the projection
/// folds).
pub(crate) fn unified_w(alpha: f64) -> f64 {
    if alpha <= 0.5 {
        alpha / (1.0 - alpha)
    } else {
        (1.0 - alpha) / alpha
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalize_rejects_zero_and_non_finite() {
        assert_eq!(normalize([0.0, 0.0, 0.0]), None);
        assert_eq!(normalize([f64::NAN, 0.0, 1.0]), None);
        assert_eq!(normalize([f64::INFINITY, 0.0, 1.0]), None);
        assert_eq!(normalize([0.0, 0.0, 3.0]), Some([0.0, 0.0, 1.0]));
    }

    #[test]
    fn unified_w_is_continuous_at_one_half() {
        assert_eq!(unified_w(0.5), 1.0);
        assert!((unified_w(0.5 + 1e-12) - 1.0).abs() < 1e-11);
        assert_eq!(unified_w(0.0), 0.0);
        assert_eq!(unified_w(1.0), 0.0);
    }
}
