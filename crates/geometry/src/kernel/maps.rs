//! Per-pixel camera maps for CAM-Convs (Facil et al., CVPR 2019) on any camera model.
//!
//! CAM-Convs concatenate maps derived from the intrinsics (centred coordinates and per-pixel
//! field-of-view angles of a pinhole camera) to the feature maps, so a network can condition on
//! where in the field of view each pixel looks. On a fisheye the pinhole maps (angles
//! `atan((u - cx) / fx)`) are not defined past 90 degrees; the paper on calibrated kernels
//! reports "abrupt changes in the feature maps" from a naive extension. Here the maps are the
//! pixel's unit viewing ray itself, which every model defines on its whole domain and which is
//! continuous across it (also beyond 180 degrees, where the angles of a pinhole parametrisation
//! jump):
//!
//! ```text
//! map 0..3 = (x, y, z) = unproject(u, v),   |(x, y, z)| = 1,   z = cos(angle to the axis)
//! map 3    = 1 where the pixel has a ray and lies on the camera image, else 0
//! ```
//!
//! A pixel without a ray, outside a fisheye's image circle (the declared field of view,
//! [`crate::camera::max_ray_angle`]) or in the input padding gets zeros
//! in all four maps. Pixel centres and scaling follow the offsets ([`super::compute_offsets`]):
//! the network input is the camera image padded by `frame.padding` on the right / bottom,
//! scaled to the feature map by `s = W_fm / (W_c + p_w)` (likewise in height), centres at
//! integer coordinates of the feature map.

use crate::camera::{max_ray_angle, Camera, CameraModel};
use crate::error::{Error, Result};

use super::InputFrame;

/// The number of maps of [`ray_maps`]: the ray's `x`, `y`, `z` and the validity mask.
pub const RAY_MAPS: usize = 4;

/// Camera maps of one feature-map size: `[RAY_MAPS, H, W]`, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RayMaps {
    pub data: Vec<f32>,
    /// `[H, W]`.
    pub size: [usize; 2],
    /// Pixels with a ray on the camera image (mask value 1).
    pub valid: usize,
}

/// The camera maps of a feature map of `size` `[H, W]` for `camera` seen through `frame`.
///
/// # Errors
/// An empty size.
pub fn ray_maps(camera: &Camera, size: [usize; 2], frame: &InputFrame) -> Result<RayMaps> {
    let [h, w] = size;
    if h == 0 || w == 0 {
        return Err(Error::InvalidArgument(format!(
            "camera maps of an empty {h}x{w} feature map"
        )));
    }
    let [w_c, h_c] = camera.size();
    let scale = [
        w as f64 / (w_c + frame.padding[0]) as f64,
        h as f64 / (h_c + frame.padding[1]) as f64,
    ];
    let cam = camera.rescaled(scale, frame.convention);
    // The camera image ends at W_c * s (padding beyond); a centre at x covers [x - 0.5, x + 0.5].
    let (x_end, y_end) = (w_c as f64 * scale[0], h_c as f64 * scale[1]);
    let max_angle = max_ray_angle(camera);
    let plane = h * w;
    let mut data = vec![0.0f32; RAY_MAPS * plane];
    let mut valid = 0;
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64, y as f64);
            if u + 0.5 > x_end + 1e-9 || v + 0.5 > y_end + 1e-9 {
                continue;
            }
            let Some(ray) = cam.unproject([u, v]) else {
                continue;
            };
            let n = (ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2]).sqrt();
            if !(n > 0.0 && n.is_finite()) {
                continue;
            }
            if max_angle.is_some_and(|max| (ray[2] / n).clamp(-1.0, 1.0).acos() > max) {
                continue;
            }
            let p = y * w + x;
            for (m, c) in ray.iter().enumerate() {
                data[m * plane + p] = (c / n) as f32;
            }
            data[3 * plane + p] = 1.0;
            valid += 1;
        }
    }
    Ok(RayMaps { data, size, valid })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped(name: &str) -> Camera {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/cameras");
        crate::camera::load(dir.join(format!("{name}.toml"))).unwrap()
    }

    fn at(m: &RayMaps, map: usize, [y, x]: [usize; 2]) -> f32 {
        m.data[map * m.size[0] * m.size[1] + y * m.size[1] + x]
    }

    #[test]
    fn rays_are_unit_vectors_pointing_where_the_camera_looks() {
        let cam = shipped("f195");
        let m = ray_maps(&cam, [36, 40], &InputFrame::default()).unwrap();
        assert!(m.valid > 0 && m.valid < 36 * 40, "{}", m.valid);
        for y in 0..36 {
            for x in 0..40 {
                let r = [0, 1, 2].map(|c| at(&m, c, [y, x]) as f64);
                let norm = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
                if at(&m, 3, [y, x]) == 1.0 {
                    assert!((norm - 1.0).abs() < 1e-6, "{norm} at {y},{x}");
                } else {
                    assert_eq!(norm, 0.0, "invalid pixel {y},{x} has a ray");
                }
            }
        }
        // Left of the centre the ray points to -x, above it to -y; near the centre along +z.
        let (cy, cx) = (18, 20);
        assert!(at(&m, 0, [cy, 2]) < -0.5 && at(&m, 0, [cy, 37]) > 0.5);
        assert!(at(&m, 1, [2, cx]) < -0.5 && at(&m, 1, [33, cx]) > 0.5);
        assert!(at(&m, 2, [cy, cx]) > 0.99);
    }

    #[test]
    fn a_pinhole_gives_the_normalised_pinhole_ray_and_padding_is_invalid() {
        let cam = shipped("pers");
        let [w_c, h_c] = cam.size();
        // The input is the image plus 4 columns of padding, at half the resolution.
        let frame = InputFrame {
            padding: [4, 0],
            ..Default::default()
        };
        let size = [h_c / 2, (w_c + 4) / 2];
        let m = ray_maps(&cam, size, &frame).unwrap();
        let scale = [
            size[1] as f64 / (w_c + 4) as f64,
            size[0] as f64 / h_c as f64,
        ];
        let scaled = cam.rescaled(scale, frame.convention);
        let ray = scaled.unproject([3.0, 5.0]).unwrap();
        let n = (ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2]).sqrt();
        for (c, r) in ray.iter().enumerate() {
            assert!((at(&m, c, [5, 3]) as f64 - r / n).abs() < 1e-6);
        }
        // The last two columns are padding (4 camera pixels = 2 feature pixels).
        for y in 0..size[0] {
            assert_eq!(at(&m, 3, [y, size[1] - 1]), 0.0);
            assert_eq!(at(&m, 3, [y, size[1] - 2]), 0.0);
            assert_eq!(at(&m, 3, [y, size[1] - 3]), 1.0);
        }
        assert!(ray_maps(&cam, [0, 4], &frame).is_err());
    }
}
