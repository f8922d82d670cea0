//! 3-vector math shared by the camera models and the kernel offsets (plain `f64`, rays
//! `[x, y, z]` in the camera frame: x right, y down, z forward; matrices row-major).

/// A row-major 3x3 matrix.
pub type Mat3 = [[f64; 3]; 3];

/// Whether every component of `v` is finite.
pub fn finite3(v: [f64; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

/// A camera's `project` of `ray` for a model whose formula divides by the distance to the
/// optical axis `q = hypot(x, y)`: `off_axis(ray, q)` where `q > 0`; on the axis the principal
/// point `centre` for a forward ray (`None` for a backward or zero one); `None` for a
/// non-finite ray.
pub fn project_off_axis(
    ray: [f64; 3],
    centre: [f64; 2],
    off_axis: impl FnOnce([f64; 3], f64) -> Option<[f64; 2]>,
) -> Option<[f64; 2]> {
    if !finite3(ray) {
        return None;
    }
    let [x, y, z] = ray;
    let q = x.hypot(y);
    if q == 0.0 {
        return (z > 0.0).then_some(centre);
    }
    off_axis(ray, q)
}

/// `v / |v|`, or `None` for a zero or non-finite vector.
pub fn normalize(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = v[0].hypot(v[1]).hypot(v[2]);
    (n > 0.0 && n.is_finite() && finite3(v)).then(|| v.map(|c| c / n))
}

/// Angle in radians between the ray `v` (any length > 0) and the optical axis `+z`, in `[0, pi]`.
pub fn angle_to_axis(v: [f64; 3]) -> f64 {
    v[0].hypot(v[1]).atan2(v[2])
}

/// The dot product `a . b`.
pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The cross product `a x b`.
pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The matrix-vector product `m v`.
pub fn rotate(m: &Mat3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
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
    fn cross_of_the_axes_is_right_handed() {
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
        let m = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rotate(&m, [1.0, 0.0, 2.0]), [0.0, 1.0, 2.0]);
    }
}
