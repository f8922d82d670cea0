//! The pinhole (perspective) camera, used for the perspective data set:
//!
//! ```text
//! u = fx x / z + cx        v = fy y / z + cy        (z > 0)
//! ```
//!
//! Pixels are `[u, v]` = (column, row) with the centre of the top-left pixel at `(0, 0)`; rays are
//! camera-frame `[x, y, z]` with z forward; angles in radians.

use super::intrinsics::deref_intrinsics;
use super::schema::{check_finite, checked, raw_camera_file, CameraFile, Checked, Invalid};
use super::{Camera, CameraModel, Intrinsics, PixelConvention};

/// A pinhole camera without distortion: its intrinsics (read as `cam.fx`, through `Deref`).
#[derive(Clone, Debug, PartialEq)]
pub struct Pinhole {
    intrinsics: Intrinsics,
}

deref_intrinsics!(Pinhole);

raw_camera_file! {
    /// A pinhole camera file as written (its field of view is derived, not stored).
    pinhole struct Raw {}
}

impl CameraFile for Pinhole {
    const MODEL: &'static str = "pinhole";
    type Raw = Raw;
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        Pinhole::new(r.intrinsics())
    }
    fn fields(&self) -> Vec<(&'static str, f64)> {
        self.intrinsics.fields().to_vec()
    }
}

impl Pinhole {
    /// A checked camera (see [`Pinhole::validate`]).
    pub fn new(intrinsics: Intrinsics) -> Result<Self, Invalid> {
        checked(Self::unchecked(intrinsics), Self::validate)
    }

    /// The camera without the checks.
    pub(crate) fn unchecked(intrinsics: Intrinsics) -> Self {
        Pinhole { intrinsics }
    }

    /// Every float finite and the intrinsics' checks ([`Intrinsics::validate`]).
    pub fn validate(&self) -> Checked {
        check_finite(self.fields())?;
        self.intrinsics.validate()
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`]:
    /// `[[fx / z, 0, -fx x / z^2], [0, fy / z, -fy y / z^2]]`, or `None` where `project` is.
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        Some([
            [self.fx / z, 0.0, -self.fx * x / (z * z)],
            [0.0, self.fy / z, -self.fy * y / (z * z)],
        ])
    }
}

impl CameraModel for Pinhole {
    /// `[fx x / z + cx, fy y / z + cy]`, or `None` for `z <= 0` or a non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        let [x, y, z] = ray;
        if !(x.is_finite() && y.is_finite() && z.is_finite()) || z <= 0.0 {
            return None;
        }
        Some([self.fx * x / z + self.cx, self.fy * y / z + self.cy])
    }

    /// The unit ray along `[(u - cx) / fx, (v - cy) / fy, 1]`; `Some` for every finite pixel.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let x = (px[0] - self.cx) / self.fx;
        let y = (px[1] - self.cy) / self.fy;
        let n = x.hypot(y).hypot(1.0);
        n.is_finite().then(|| [x / n, y / n, 1.0 / n])
    }

    fn size(&self) -> [usize; 2] {
        self.intrinsics.size()
    }
    /// `2 atan(width / (2 fx))`: the angle between the left and right image edges (pixel edges at
    /// `-0.5` and `width - 0.5`) when the principal point is centred (`cx = (width - 1) / 2`).
    /// For an off-centre `cx` the true edge-to-edge angle is
    /// `atan((cx + 0.5) / fx) + atan((width - 0.5 - cx) / fx)`, slightly smaller.
    fn fov(&self) -> f64 {
        2.0 * (self.width as f64 / (2.0 * self.fx)).atan()
    }

    /// The intrinsics rescaled ([`Intrinsics::rescaled`]).
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        Camera::Pinhole(Pinhole {
            intrinsics: self.intrinsics.rescaled(scale, convention),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Round trips of a division and a normalisation: a few ulps of ~1e3 px; 1e-9 px is margin.
    const PX_TOL: f64 = 1e-9;

    fn pers() -> Pinhole {
        Pinhole::new(Intrinsics {
            fx: 540.0,
            fy: 540.0,
            cx: 540.0,
            cy: 480.0,
            width: 1080,
            height: 960,
        })
        .unwrap()
    }

    #[test]
    fn principal_point_and_behind_the_camera() {
        let cam = pers();
        assert_eq!(cam.unproject([540.0, 480.0]), Some([0.0, 0.0, 1.0]));
        assert_eq!(cam.project([0.0, 0.0, 3.0]), Some([540.0, 480.0]));
        assert_eq!(cam.project([0.1, 0.2, -1.0]), None);
        assert_eq!(cam.project([1.0, 0.0, 0.0]), None);
        assert_eq!(cam.project([0.0, 0.0, 0.0]), None);
        assert_eq!(cam.project([f64::NAN, 0.0, 1.0]), None);
        assert_eq!(cam.unproject([f64::INFINITY, 0.0]), None);
    }

    #[test]
    fn round_trip_and_fov() {
        let cam = pers();
        let px = [12.25, 901.5];
        let ray = cam.unproject(px).unwrap();
        assert!((ray[0].hypot(ray[1]).hypot(ray[2]) - 1.0).abs() < 1e-15);
        for len in [0.1, 1.0, 10.0] {
            let back = cam.project(ray.map(|c| c * len)).unwrap();
            assert!((back[0] - px[0]).abs() < PX_TOL && (back[1] - px[1]).abs() < PX_TOL);
        }
        // fx = width / 2: 90 degrees.
        assert!((cam.fov() - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
    }

    #[test]
    fn rescaled_by_both_conventions() {
        let cam = pers();
        // fx 540 * 0.5, fy 540 * 0.25, cx 540.5 * 0.5 - 0.5, cy 480.5 * 0.25 - 0.5.
        let half = Pinhole::new(Intrinsics {
            fx: 270.0,
            fy: 135.0,
            cx: 269.75,
            cy: 119.625,
            width: 540,
            height: 240,
        })
        .unwrap();
        let paper = Pinhole::new(Intrinsics {
            cx: 270.0,
            cy: 120.0,
            ..*half
        })
        .unwrap();
        assert_eq!(
            cam.rescaled([0.5, 0.25], PixelConvention::HalfPixel),
            Camera::Pinhole(half)
        );
        assert_eq!(
            cam.rescaled([0.5, 0.25], PixelConvention::Paper),
            Camera::Pinhole(paper)
        );
    }
}
