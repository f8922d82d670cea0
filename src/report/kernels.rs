//! The deformed-kernel figure (paper Figure 1a): calibrated kernels drawn over a fisheye image.
//!
//! Kernels are computed on a coarse feature map (the camera image, plus its padding, divided by
//! `level`) so that a 3x3 kernel spans enough image pixels to be seen, then mapped back to image
//! pixels with the inverse of the same scaling and pixel convention as the offsets.

use std::path::Path;

use image::RgbImage;

use super::draw;
use crate::camera::{Camera, CameraModel, PixelConvention};
use crate::error::{Error, Result};
use crate::kernel::{cached_offsets, InputFrame, LayerGeometry};

/// Options of the kernel figure.
#[derive(Clone, Debug)]
pub struct KernelFigure {
    /// Feature-map downsampling factor the kernels are computed at (16 = a U-Net's 4th level).
    pub level: usize,
    /// Kernel size (odd).
    pub kernel: usize,
    /// Number of kernels along the longer image side.
    pub grid: usize,
    pub frame: InputFrame,
}

impl Default for KernelFigure {
    fn default() -> Self {
        KernelFigure {
            level: 16,
            kernel: 3,
            grid: 9,
            frame: InputFrame::default(),
        }
    }
}

/// A background for `camera`: the image circle (rays within the field of view) in dark grey,
/// the rest black, with a ring every 30 degrees of incidence angle.
pub fn image_circle(camera: &Camera) -> RgbImage {
    let [w, h] = camera.size();
    let half_fov = camera.fov() / 2.0;
    RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let theta = camera
            .unproject([x as f64, y as f64])
            .map(|r| r[2].clamp(-1.0, 1.0).acos());
        let v = match theta {
            Some(t) if t <= half_fov => {
                let ring = (t.to_degrees() / 30.0).fract();
                if !(0.02..=0.98).contains(&ring) && t > 0.1 {
                    90
                } else {
                    55
                }
            }
            _ => 0,
        };
        image::Rgb([v, v, v])
    })
}

/// Reads a background image that must have the camera's size.
pub fn load_background(path: &Path, camera: &Camera) -> Result<RgbImage> {
    let img = image::open(path)
        .map_err(|e| Error::Image {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?
        .to_rgb8();
    let [w, h] = camera.size();
    if (img.width() as usize, img.height() as usize) != (w, h) {
        return Err(Error::Image {
            path: path.to_path_buf(),
            message: format!(
                "image is {}x{} but the camera is {w}x{h} (width x height)",
                img.width(),
                img.height()
            ),
        });
    }
    Ok(img)
}

/// Draws a grid of calibrated kernels over `background` (the camera's image).
pub fn draw_kernels(
    camera: &Camera,
    mut background: RgbImage,
    fig: &KernelFigure,
) -> Result<RgbImage> {
    let [w_c, h_c] = camera.size();
    let (w_in, h_in) = (w_c + fig.frame.padding[0], h_c + fig.frame.padding[1]);
    let fm = [h_in / fig.level.max(1), w_in / fig.level.max(1)];
    let geometry = LayerGeometry::same(fig.kernel);
    let offsets = cached_offsets(camera, fm, &geometry, &fig.frame)?;
    // Feature-map pixel -> image pixel: the inverse of the intrinsics scaling.
    let scale = [fm[1] as f64 / w_in as f64, fm[0] as f64 / h_in as f64];
    let to_image = |u: f64, s: f64| match fig.frame.convention {
        PixelConvention::HalfPixel => (u + 0.5) / s - 0.5,
        PixelConvention::Paper => u / s,
    };
    let k = fig.kernel;
    let c = (k - 1) / 2;
    let longer = fm[0].max(fm[1]);
    let step = (longer / fig.grid.max(1)).max(1);
    let dot = (1.5f64).max(w_c as f64 / 400.0);
    for oy in (step / 2..fm[0]).step_by(step) {
        for ox in (step / 2..fm[1]).step_by(step) {
            let tap = |i: usize, j: usize| {
                let [dy, dx] = offsets.get([i, j], [oy, ox]);
                let y = oy as f64 + i as f64 - c as f64 + dy as f64;
                let x = ox as f64 + j as f64 - c as f64 + dx as f64;
                [to_image(x, scale[0]), to_image(y, scale[1])]
            };
            let colour = [255, 90, 40];
            for i in 0..k {
                for j in 0..k {
                    if j + 1 < k {
                        draw::line(
                            &mut background,
                            tap(i, j),
                            tap(i, j + 1),
                            dot * 0.6,
                            [240, 200, 60],
                        );
                    }
                    if i + 1 < k {
                        draw::line(
                            &mut background,
                            tap(i, j),
                            tap(i + 1, j),
                            dot * 0.6,
                            [240, 200, 60],
                        );
                    }
                }
            }
            for i in 0..k {
                for j in 0..k {
                    let [x, y] = tap(i, j);
                    let col = if i == c && j == c {
                        [80, 200, 255]
                    } else {
                        colour
                    };
                    draw::disc(&mut background, x, y, dot, col);
                }
            }
        }
    }
    Ok(background)
}
