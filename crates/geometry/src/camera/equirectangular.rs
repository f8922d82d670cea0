//! The equirectangular (longitude-latitude) panorama: the whole sphere on a `width x height`
//! grid, as in 360-degree data sets (Stanford 2D-3D-S, Matterport3D) and the distortion-aware
//! convolutions of Tateno et al. (ECCV 2018) and Fernandez-Labrador et al. (EquiConvs, 2020).
//!
//! Conventions (camera frame x right, y down, z forward; pixels `[u, v]` = (column, row) with the
//! centre of the top-left pixel at `(0, 0)`):
//!
//! ```text
//! longitude lon = atan2(x, z)                 in [-pi, pi]: 0 forward (+z), +pi/2 right (+x)
//! latitude  lat = atan2(-y, sqrt(x^2 + z^2))  in [-pi/2, pi/2]: +pi/2 up (-y)
//! u = cu + fu lon,  v = cv - fv lat,   fu = width / (2 pi),  fv = height / pi,
//! cu = width / 2 - 0.5,  cv = height / 2 - 0.5
//! ray(u, v) = [cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon)]
//! ```
//!
//! So the pixel grid's outer edges are exact: `u = -0.5` is longitude `-pi` and `u = width - 0.5`
//! is `+pi` (the seam, looking backward), `v = -0.5` is the north pole (straight up) and
//! `v = height - 0.5` the south pole; column `j` has its centre at longitude
//! `(j + 0.5) 2 pi / width - pi`, and the image centre `(cu, cv)` looks forward. The rows
//! `v = -0.5` and `v = height - 0.5` are the poles; every finite `u` unprojects (longitude is
//! periodic), `v` outside `[-0.5, height - 0.5]` does not. At a pole `atan2(0, 0) = 0` (or `pi`)
//! picks a longitude, so projecting the vertical ray gives a pixel, never NaN.
//!
//! Kernels wrap horizontally across the seam ([`CameraModel::wraps_horizontally`]): the offsets and
//! the sampling plan take columns modulo the feature-map width. They are oriented upright
//! ([`KernelFrame::Upright`]: rows along the parallels), so a kernel's offsets depend on its row
//! only.

use std::f64::consts::PI;

use crate::vec3::finite3;

/// Relative slack on the latitude of the outer pixel edges `v = -0.5` and `v = height - 0.5`:
/// `(cv + 0.5) / fv` is `pi / 2` only up to the rounding of `fv = height / pi` (an ulp or two), and
/// the pole rows must unproject; latitudes within the slack are clamped to the pole.
const POLE_SLACK: f64 = 1e-12;
use super::schema::{check_size, checked, raw_camera_file, CameraFile, Checked, Invalid};
use super::{Camera, CameraModel, KernelFrame, PixelConvention};

/// An equirectangular panorama camera.
///
/// [`Equirectangular::new`] derives the angular scale and centre from the image size; they are
/// kept as fields so that [`CameraModel::rescaled`] can move them by a pixel convention like any
/// other model's intrinsics.
#[derive(Clone, Debug, PartialEq)]
pub struct Equirectangular {
    /// Image width in pixels (360 degrees of longitude).
    pub width: usize,
    /// Image height in pixels (180 degrees of latitude).
    pub height: usize,
    /// Pixels per radian of longitude (`width / (2 pi)` at the native size).
    pub fu: f64,
    /// Pixels per radian of latitude (`height / pi` at the native size).
    pub fv: f64,
    /// Column of longitude 0 (`width / 2 - 0.5` at the native size).
    pub cu: f64,
    /// Row of latitude 0 (`height / 2 - 0.5` at the native size).
    pub cv: f64,
}

raw_camera_file! {
    /// An equirectangular panorama file as written: only the size.
    struct Raw {
        width: usize,
        height: usize,
    }
}

impl CameraFile for Equirectangular {
    const MODEL: &'static str = "equirectangular";
    type Raw = Raw;
    fn from_raw(r: Raw) -> Result<Self, Invalid> {
        Equirectangular::new(r.width, r.height)
    }
    fn fields(&self) -> Vec<(&'static str, f64)> {
        Vec::new()
    }
}

impl Equirectangular {
    /// A full-sphere panorama of `width x height` pixels (module docs), both `> 0`.
    pub fn new(width: usize, height: usize) -> Result<Self, Invalid> {
        checked(Self::unchecked(width, height), Self::validate)
    }

    /// `width, height > 0`.
    pub fn validate(&self) -> Checked {
        check_size(self.width, self.height)
    }

    fn unchecked(width: usize, height: usize) -> Self {
        Equirectangular {
            width,
            height,
            fu: width as f64 / (2.0 * PI),
            fv: height as f64 / PI,
            cu: width as f64 / 2.0 - 0.5,
            cv: height as f64 / 2.0 - 0.5,
        }
    }

    /// `[longitude, latitude]` in radians of a ray (module docs), or `None` for a zero or
    /// non-finite ray.
    pub fn lon_lat(ray: [f64; 3]) -> Option<[f64; 2]> {
        let [x, y, z] = ray;
        let q = x.hypot(z);
        if !finite3(ray) || (q == 0.0 && y == 0.0) {
            return None;
        }
        Some([x.atan2(z), (-y).atan2(q)])
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`], or `None` where
    /// `project` is `None` and at the poles (`x = z = 0`, where longitude is not differentiable).
    /// With `q^2 = x^2 + z^2`, `n^2 = q^2 + y^2`:
    ///
    /// ```text
    /// du/dx = fu z / q^2          du/dy = 0            du/dz = -fu x / q^2
    /// dv/dx = -fv x y / (q n^2)   dv/dy = fv q / n^2   dv/dz = -fv y z / (q n^2)
    /// ```
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        self.project(ray)?;
        let [x, y, z] = ray;
        let q2 = x * x + z * z;
        if q2 == 0.0 {
            return None;
        }
        let q = q2.sqrt();
        let n2 = q2 + y * y;
        Some([
            [self.fu * z / q2, 0.0, -self.fu * x / q2],
            [
                -self.fv * x * y / (q * n2),
                self.fv * q / n2,
                -self.fv * y * z / (q * n2),
            ],
        ])
    }
}

impl CameraModel for Equirectangular {
    /// `[cu + fu lon, cv - fv lat]` (module docs); `u` lies in `[cu - fu pi, cu + fu pi]`
    /// (`[-0.5, width - 0.5]` at the native size). `None` only for a zero or non-finite ray.
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        let [lon, lat] = Self::lon_lat(ray)?;
        Some([self.cu + self.fu * lon, self.cv - self.fv * lat])
    }

    /// The unit ray of longitude `(u - cu) / fu` and latitude `(cv - v) / fv`; `None` for a
    /// latitude beyond a pole or a non-finite pixel. Any finite `u` unprojects (periodic).
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        let lon = (px[0] - self.cu) / self.fu;
        let lat = (self.cv - px[1]) / self.fv;
        if !(lon.is_finite() && lat.abs() <= PI / 2.0 * (1.0 + POLE_SLACK)) {
            return None;
        }
        let lat = lat.clamp(-PI / 2.0, PI / 2.0);
        let (sl, cl) = lat.sin_cos();
        let (so, co) = lon.sin_cos();
        Some([cl * so, -sl, cl * co])
    }

    fn size(&self) -> [usize; 2] {
        [self.width, self.height]
    }

    /// `2 pi`: the panorama spans the full circle horizontally.
    fn fov(&self) -> f64 {
        2.0 * PI
    }

    /// `fu sx`, `fv sy`, the centre moved by `convention`, size `round(width sx)` x
    /// `round(height sy)`.
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        let [sx, sy] = scale;
        Camera::Equirectangular(Equirectangular {
            width: (self.width as f64 * sx).round() as usize,
            height: (self.height as f64 * sy).round() as usize,
            fu: self.fu * sx,
            fv: self.fv * sy,
            cu: convention.scale_centre(self.cu, sx),
            cv: convention.scale_centre(self.cv, sy),
        })
    }

    /// `true`: longitude is periodic, kernels continue across the seam.
    fn wraps_horizontally(&self) -> bool {
        true
    }

    /// [`KernelFrame::Upright`]: kernels keep their rows along the parallels, the same at every
    /// longitude (the minimal rotation from the forward axis would spin them around the point
    /// straight back, which lies on the seam).
    fn kernel_frame(&self) -> KernelFrame {
        KernelFrame::Upright
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Trigonometric round trips: a few ulps of angles times ~1e2 px/rad; 1e-9 px is margin.
    const PX_TOL: f64 = 1e-9;
    /// Unit-vector components from sin/cos of exact angles: within an ulp or two of 1 (2.2e-16).
    const UNIT_TOL: f64 = 1e-15;
    /// Angles from atan2 of computed components: a few ulps of pi; 1e-12 rad is margin.
    const RAD_TOL: f64 = 1e-12;

    #[test]
    fn grid_edges_centre_and_poles() {
        let c = Equirectangular::new(1024, 512).unwrap();
        // Centre: forward.
        assert_eq!(c.unproject([511.5, 255.5]), Some([0.0, -0.0, 1.0]));
        assert_eq!(c.project([0.0, 0.0, 2.0]), Some([511.5, 255.5]));
        // Right (+x) is longitude +90 deg: a quarter of the width right of the centre.
        let [u, v] = c.project([3.0, 0.0, 0.0]).unwrap();
        assert!((u - (511.5 + 256.0)).abs() < PX_TOL && (v - 255.5).abs() < PX_TOL);
        // Up (-y) is the north pole, the top edge of the top row; no NaN at either pole.
        let [_, v] = c.project([0.0, -1.0, 0.0]).unwrap();
        assert!((v + 0.5).abs() < PX_TOL);
        let [u, v] = c.project([0.0, 1.0, 0.0]).unwrap();
        assert!(u.is_finite() && (v - 511.5).abs() < PX_TOL);
        let north = c.unproject([100.0, -0.5]).unwrap();
        assert!(north.iter().all(|x| x.is_finite()) && (north[1] + 1.0).abs() < UNIT_TOL);
        // Backward is the seam: the left and right outer edges.
        let left = c.unproject([-0.5, 255.5]).unwrap();
        let right = c.unproject([1023.5, 255.5]).unwrap();
        assert!((left[2] + 1.0).abs() < UNIT_TOL && (right[2] + 1.0).abs() < UNIT_TOL);
        let [u, _] = c.project([1e-300, 0.0, -1.0]).unwrap();
        assert!((u - 1023.5).abs() < PX_TOL, "{u}");
        let [u, _] = c.project([-1e-300, 0.0, -1.0]).unwrap();
        assert!((u + 0.5).abs() < PX_TOL, "{u}");
        // Longitude is periodic in u; latitude ends at the poles.
        let a = c.unproject([10.0, 100.0]).unwrap();
        let b = c.unproject([10.0 + 1024.0, 100.0]).unwrap();
        assert!((0..3).all(|i| (a[i] - b[i]).abs() < RAD_TOL));
        assert_eq!(c.unproject([10.0, -0.6]), None);
        assert_eq!(c.unproject([10.0, 511.6]), None);
        assert_eq!(c.project([0.0, 0.0, 0.0]), None);
        assert_eq!(c.project([f64::NAN, 0.0, 1.0]), None);
    }

    #[test]
    fn pole_edges_unproject_at_every_size() {
        for (w, h) in [
            (360, 180),
            (1000, 500),
            (4096, 2048),
            (1023, 511),
            (64, 32),
            (7, 3),
        ] {
            let native = Equirectangular::new(w, h).unwrap();
            let Camera::Equirectangular(half) =
                native.rescaled([0.5, 0.5], PixelConvention::HalfPixel)
            else {
                unreachable!()
            };
            for c in [native, half] {
                let bottom = c.cv + c.fv * PI / 2.0;
                let top = c.cv - c.fv * PI / 2.0;
                let n = c
                    .unproject([3.0, top])
                    .unwrap_or_else(|| panic!("{w}x{h} top"));
                let s = c
                    .unproject([3.0, bottom])
                    .unwrap_or_else(|| panic!("{w}x{h} bottom"));
                assert!(n[1] < -1.0 + UNIT_TOL && s[1] > 1.0 - UNIT_TOL, "{w}x{h}");
                assert_eq!(c.unproject([3.0, top - 1e-6]), None, "{w}x{h}");
            }
        }
    }

    #[test]
    fn column_centres_are_at_documented_longitudes() {
        let c = Equirectangular::new(360, 180).unwrap();
        for j in [0usize, 1, 179, 359] {
            let ray = c.unproject([j as f64, 89.5]).unwrap();
            let want = (j as f64 + 0.5) * 2.0 * PI / 360.0 - PI;
            assert!((ray[0].atan2(ray[2]) - want).abs() < RAD_TOL, "{j}");
        }
    }
}
