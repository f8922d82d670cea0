//! Point clouds from depth maps (paper Fig. 4): every valid pixel back-projected with the camera
//! model, as a PLY file and a top view.
//!
//! Conventions: pixel `(u, v)` = (column, row) of the network input, whose top-left pixel centre
//! is `(0, 0)` and whose padding lies right / bottom, so input pixels are camera pixels. Depth is
//! the distance along the ray (the synthetic data's metric distance), so a point is
//! `d * r / |r|` with `r = unproject(u, v)`. Camera frame: x right, y down, z forward; the top
//! view looks down the -y axis (x to the right, z up the picture).

use std::path::Path;

use crate::camera::{Camera, CameraModel};
use crate::error::Result;
use crate::io::{write_bytes_atomic, write_png_atomic};

/// A coloured point, camera frame, metres.
pub type Point = ([f32; 3], [u8; 3]);

/// Back-projects `depth` (`[H, W]` row-major, metres, `<= 0` missing) where `valid`, coloured by
/// `rgb`; pixels the camera cannot unproject are left out.
pub fn back_project(
    camera: &Camera,
    size: [usize; 2],
    depth: &[f32],
    valid: &[bool],
    rgb: &[[u8; 3]],
) -> Vec<Point> {
    let [h, w] = size;
    let mut out = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let d = depth[i];
            if !valid[i] || d <= 0.0 || !d.is_finite() {
                continue;
            }
            let Some(r) = camera.unproject([u as f64, v as f64]) else {
                continue;
            };
            let n = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            if n <= 0.0 {
                continue;
            }
            let s = d as f64 / n;
            out.push((
                [(r[0] * s) as f32, (r[1] * s) as f32, (r[2] * s) as f32],
                rgb[i],
            ));
        }
    }
    out
}

/// An ASCII PLY of `points` (x y z red green blue).
pub fn write_ply(path: &Path, points: &[Point]) -> Result<()> {
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment calibconv report: camera frame, metres\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty uchar red\n\
         property uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    for (p, c) in points {
        s += &format!("{} {} {} {} {} {}\n", p[0], p[1], p[2], c[0], c[1], c[2]);
    }
    write_bytes_atomic(path, s.as_bytes())
}

/// A top view (`size` px square) of point sets, each drawn in one colour, later sets on top;
/// the camera is a black dot at the bottom centre, the extent the largest |x|, z of all sets.
pub fn top_view(path: &Path, sets: &[(&[Point], [u8; 3])], size: u32) -> Result<()> {
    let mut img = super::draw::canvas(size, size, [255, 255, 255]);
    let extent = sets
        .iter()
        .flat_map(|(s, _)| s.iter())
        .map(|(p, _)| p[0].abs().max(p[2].abs()))
        .fold(0.0f32, f32::max)
        .max(1e-3) as f64;
    let scale = (size as f64 * 0.48) / extent;
    let to_px = |x: f32, z: f32| {
        [
            size as f64 / 2.0 + x as f64 * scale,
            size as f64 * 0.5 - z as f64 * scale,
        ]
    };
    for (points, colour) in sets {
        for (p, _) in points.iter() {
            let [x, y] = to_px(p[0], p[2]);
            super::draw::disc(&mut img, x, y, 1.0, *colour);
        }
    }
    let [cx, cy] = to_px(0.0, 0.0);
    super::draw::disc(&mut img, cx, cy, 4.0, [0, 0, 0]);
    write_png_atomic(path, &img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn back_projection_puts_points_at_their_distance_along_the_ray() {
        let camera = crate::camera::shipped("f195");
        let s = 16.0 / 1080.0;
        let camera = camera.rescaled([s, s], crate::camera::PixelConvention::HalfPixel);
        let [w, h] = camera.size();
        let n = w * h;
        let pts = back_project(
            &camera,
            [h, w],
            &vec![2.5; n],
            &vec![true; n],
            &vec![[1, 2, 3]; n],
        );
        assert!(!pts.is_empty());
        for (p, c) in &pts {
            let d = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((d - 2.5).abs() < 1e-4, "{d}");
            assert_eq!(*c, [1, 2, 3]);
        }
        let dir = tempfile::tempdir().unwrap();
        write_ply(&dir.path().join("a.ply"), &pts).unwrap();
        let text = std::fs::read_to_string(dir.path().join("a.ply")).unwrap();
        assert!(text.contains(&format!("element vertex {}\n", pts.len())));
        assert_eq!(text.lines().count(), 11 + pts.len()); // 11 header lines
        top_view(&dir.path().join("a.png"), &[(&pts, [0, 0, 255])], 64).unwrap();
    }
}
