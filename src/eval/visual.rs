//! Pictures of predictions: colour maps and side-by-side panels (RGB | ground truth |
//! prediction, and for depth the absolute error), for PNGs and TensorBoard.
//!
//! Depth is coloured with a perceptual map from near (dark blue) to far (yellow) over
//! `[0, max ground truth of the image]`, so prediction and ground truth share one scale; the
//! error panel maps `[0, that max / 4]`. Invalid pixels (mask false) are black. Classes use a
//! fixed palette; unknown / invalid labels are black.

use image::RgbImage;
use tch::{Kind, Tensor};

use crate::error::Result;

/// Control points of the depth colour map (viridis at 0, 1/8, ..., 1).
const DEPTH_MAP: [[f32; 3]; 9] = [
    [68.0, 1.0, 84.0],
    [71.0, 44.0, 122.0],
    [59.0, 81.0, 139.0],
    [44.0, 113.0, 142.0],
    [33.0, 144.0, 141.0],
    [39.0, 173.0, 129.0],
    [92.0, 200.0, 99.0],
    [170.0, 220.0, 50.0],
    [253.0, 231.0, 37.0],
];

/// One colour per class (13 Stanford classes first, then repeats), RGB.
pub const PALETTE: [[u8; 3]; 16] = [
    [230, 25, 75],
    [60, 180, 75],
    [255, 225, 25],
    [0, 130, 200],
    [245, 130, 48],
    [145, 30, 180],
    [70, 240, 240],
    [240, 50, 230],
    [210, 245, 60],
    [250, 190, 212],
    [0, 128, 128],
    [220, 190, 255],
    [170, 110, 40],
    [255, 250, 200],
    [128, 0, 0],
    [170, 255, 195],
];

/// The colour of `t` in `[0, 1]` (clamped).
pub fn depth_colour(t: f32) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let x = t * (DEPTH_MAP.len() - 1) as f32;
    let i = (x.floor() as usize).min(DEPTH_MAP.len() - 2);
    let f = x - i as f32;
    let (a, b) = (DEPTH_MAP[i], DEPTH_MAP[i + 1]);
    [0, 1, 2].map(|c| (a[c] + (b[c] - a[c]) * f).round() as u8)
}

fn plane(t: &Tensor) -> Result<(Vec<f32>, usize, usize)> {
    let s = t.size();
    let (h, w) = (s[s.len() - 2] as usize, s[s.len() - 1] as usize);
    let v = Vec::<f32>::try_from(t.to_kind(Kind::Float).flatten(0, -1))?;
    Ok((v, h, w))
}

/// An RGB image from a `[3, H, W]` float tensor in `[0, 1]`.
pub fn rgb_image(image: &Tensor) -> Result<RgbImage> {
    let s = image.size();
    let (h, w) = (s[1] as u32, s[2] as u32);
    let hwc = (image.to_kind(Kind::Float).clamp(0.0, 1.0) * 255.0)
        .round()
        .permute([1, 2, 0])
        .contiguous()
        .to_kind(Kind::Uint8);
    let bytes = Vec::<u8>::try_from(hwc.flatten(0, -1))?;
    Ok(RgbImage::from_raw(w, h, bytes).expect("size matches"))
}

/// A depth map `[1, H, W]` (or `[H, W]`) coloured over `[0, max]`; pixels where `mask` is false
/// are black.
pub fn depth_image(depth: &Tensor, mask: &Tensor, max: f32) -> Result<RgbImage> {
    let (d, h, w) = plane(depth)?;
    let (m, _, _) = plane(&mask.to_kind(Kind::Float))?;
    let mut img = RgbImage::new(w as u32, h as u32);
    for (i, px) in img.pixels_mut().enumerate() {
        if m[i] > 0.5 {
            px.0 = depth_colour(d[i] / max.max(1e-6));
        }
    }
    Ok(img)
}

/// Class ids `[H, W]` coloured with [`PALETTE`]; negative ids (unknown) are black.
pub fn label_image(labels: &Tensor) -> Result<RgbImage> {
    let s = labels.size();
    let (h, w) = (s[s.len() - 2] as u32, s[s.len() - 1] as u32);
    let v = Vec::<i64>::try_from(labels.to_kind(Kind::Int64).flatten(0, -1))?;
    let mut img = RgbImage::new(w, h);
    for (px, &c) in img.pixels_mut().zip(&v) {
        if c >= 0 {
            px.0 = PALETTE[c as usize % PALETTE.len()];
        }
    }
    Ok(img)
}

/// Images side by side, separated by a 2-pixel white gap.
pub fn hstack(images: &[RgbImage]) -> RgbImage {
    const GAP: u32 = 2;
    let h = images.iter().map(|i| i.height()).max().unwrap_or(0);
    let w =
        images.iter().map(|i| i.width()).sum::<u32>() + GAP * images.len().saturating_sub(1) as u32;
    let mut out = RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let mut x = 0;
    for img in images {
        image::imageops::replace(&mut out, img, x as i64, 0);
        x += img.width() + GAP;
    }
    out
}

/// RGB | ground truth | prediction | |error| for one depth sample.
///
/// # Shapes
/// `image` `[3, H, W]`, `gt` / `pred` `[1, H, W]` metres, `mask` `[1, H, W]` bool.
pub fn depth_panel(image: &Tensor, gt: &Tensor, pred: &Tensor, mask: &Tensor) -> Result<RgbImage> {
    let valid = mask.logical_and(&gt.gt(0.0));
    let max = gt
        .masked_select(&valid)
        .max_other(&Tensor::from(1e-3f32))
        .max()
        .double_value(&[]) as f32;
    let err = (pred - gt).abs();
    Ok(hstack(&[
        rgb_image(image)?,
        depth_image(gt, &valid, max)?,
        depth_image(pred, mask, max)?,
        depth_image(&err, &valid, max / 4.0)?,
    ]))
}

/// RGB | ground truth | prediction for one segmentation sample.
///
/// # Shapes
/// `image` `[3, H, W]`, `labels` `[H, W]` int64, `pred` `[H, W]` int64 predicted classes,
/// `mask` `[1, H, W]` bool (prediction shown where true or where a label exists).
pub fn segmentation_panel(
    image: &Tensor,
    labels: &Tensor,
    pred: &Tensor,
    mask: &Tensor,
) -> Result<RgbImage> {
    let show = mask.squeeze_dim(0).logical_or(&labels.ge(0));
    let pred = pred.where_scalarother(&show, -1);
    Ok(hstack(&[
        rgb_image(image)?,
        label_image(labels)?,
        label_image(&pred)?,
    ]))
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    #[test]
    fn colours_and_panels() {
        assert_eq!(depth_colour(0.0), [68, 1, 84]);
        assert_eq!(depth_colour(1.0), [253, 231, 37]);
        assert_eq!(depth_colour(2.0), [253, 231, 37]);
        assert_eq!(depth_colour(f32::NAN), [253, 231, 37]);
        let img = Tensor::rand([3, 4, 5], (Kind::Float, Device::Cpu));
        let gt = Tensor::rand([1, 4, 5], (Kind::Float, Device::Cpu)) + 0.5;
        // At least one invalid pixel whatever the draw (regression: 1% of draws had none).
        let _ = gt.get(0).get(2).get(3).fill_(0.6);
        let mask = gt.gt(0.7);
        let p = depth_panel(&img, &gt, &gt, &mask).unwrap();
        assert_eq!((p.width(), p.height()), (4 * 5 + 3 * 2, 4));
        // Masked pixels are black in the ground-truth panel.
        let m = Vec::<bool>::try_from(mask.flatten(0, -1)).unwrap();
        let first_masked = m.iter().position(|v| !v).unwrap();
        let (x, y) = ((first_masked % 5) as u32, (first_masked / 5) as u32);
        assert_eq!(p.get_pixel(5 + 2 + x, y).0, [0, 0, 0]);
        let labels = Tensor::from_slice(&[0i64, 1, -100, 2]).view([2, 2]);
        let s = segmentation_panel(
            &img.narrow(1, 0, 2).narrow(2, 0, 2),
            &labels,
            &labels,
            &labels.ge(0).unsqueeze(0),
        )
        .unwrap();
        assert_eq!(s.get_pixel(4, 1).0, [0, 0, 0]); // the unknown label
        assert_eq!(s.get_pixel(4, 0).0, PALETTE[0]);
    }
}
