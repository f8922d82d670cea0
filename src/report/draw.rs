//! Minimal raster drawing on `image::RgbImage` (lines, discs, alpha blending).

use image::{Rgb, RgbImage};

/// Blends `colour` into pixel `(x, y)` with opacity `alpha` (ignored outside the image).
pub fn blend(img: &mut RgbImage, x: i64, y: i64, colour: [u8; 3], alpha: f32) {
    if x < 0 || y < 0 || x >= img.width() as i64 || y >= img.height() as i64 {
        return;
    }
    let p = img.get_pixel_mut(x as u32, y as u32);
    for (v, c) in p.0.iter_mut().zip(colour) {
        *v = (*v as f32 * (1.0 - alpha) + c as f32 * alpha).round() as u8;
    }
}

/// A filled disc of `radius` pixels centred at `(cx, cy)`.
pub fn disc(img: &mut RgbImage, cx: f64, cy: f64, radius: f64, colour: [u8; 3]) {
    let r = radius.ceil() as i64 + 1;
    let (x0, y0) = (cx.round() as i64, cy.round() as i64);
    for y in y0 - r..=y0 + r {
        for x in x0 - r..=x0 + r {
            let d = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt();
            // One pixel of anti-aliasing at the rim.
            let a = (radius + 0.5 - d).clamp(0.0, 1.0) as f32;
            if a > 0.0 {
                blend(img, x, y, colour, a);
            }
        }
    }
}

/// A line segment of `width` pixels from `a` to `b` (`[x, y]`), drawn as overlapping discs.
pub fn line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], width: f64, colour: [u8; 3]) {
    let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
    let steps = (len * 2.0).ceil().max(1.0) as usize;
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        if width <= 1.0 {
            blend(img, x.round() as i64, y.round() as i64, colour, 1.0);
        } else {
            disc(img, x, y, width / 2.0, colour);
        }
    }
}

/// An image of `width x height` filled with `colour`.
pub fn canvas(width: u32, height: u32, colour: [u8; 3]) -> RgbImage {
    RgbImage::from_pixel(width, height, Rgb(colour))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_covers_its_endpoints_and_nothing_far_away() {
        let mut img = canvas(20, 10, [0, 0, 0]);
        line(&mut img, [2.0, 2.0], [17.0, 7.0], 1.0, [255, 0, 0]);
        assert_eq!(img.get_pixel(2, 2).0, [255, 0, 0]);
        assert_eq!(img.get_pixel(17, 7).0, [255, 0, 0]);
        assert_eq!(img.get_pixel(17, 1).0, [0, 0, 0]);
    }
}
