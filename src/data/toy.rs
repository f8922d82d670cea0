//! A tiny learnable task generated in memory, for tests, smoke runs and timing before (or
//! without) a real data set: flat-coloured rectangles and discs on a background.
//!
//! - RGB: each region has a class colour ([`TOY_COLOURS`]) times a shade in `[0.55, 1]`, plus a
//!   vertical light gradient (`+-0.08`); values in `[0, 1]`.
//! - Depth (metres) is a smooth function of brightness: `1 + 8 (1 - luminance)`, luminance the
//!   mean of RGB, so it is learnable from the image alone.
//! - Labels: the region's class (`0..NUM_CLASSES`); about one region in ten is "unknown"
//!   (grey, label `IGNORE_LABEL`, depth still valid).
//! - Mask: with a camera, the pixels of the network input that see inside the camera's field of
//!   view (the fisheye image circle) and are not padding; outside it RGB and depth are 0 and
//!   labels are `IGNORE_LABEL`, as the data contract says.
//!
//! Content is a pure function of the content seed and the sample index, so splits generated
//! with different seeds are different and every run sees the same pixels.

use tch::{Device, Kind, Tensor};

use super::memory::{MemorySource, SplitMix64};
use super::{IGNORE_LABEL, NUM_CLASSES};
use crate::camera::{Camera, CameraModel};
use crate::error::{Error, Result};
use crate::kernel::InputFrame;

/// Base colour of each class (RGB in `[0, 1]`).
pub const TOY_COLOURS: [[f32; 3]; NUM_CLASSES] = [
    [0.90, 0.10, 0.10],
    [0.10, 0.80, 0.20],
    [0.15, 0.25, 0.95],
    [0.95, 0.85, 0.10],
    [0.85, 0.20, 0.85],
    [0.10, 0.85, 0.85],
    [0.95, 0.55, 0.10],
    [0.55, 0.30, 0.10],
    [0.60, 0.95, 0.40],
    [0.45, 0.15, 0.65],
    [0.95, 0.60, 0.70],
    [0.30, 0.55, 0.45],
    [0.85, 0.85, 0.95],
];

/// Colour of "unknown" regions.
const UNKNOWN_COLOUR: [f32; 3] = [0.5, 0.5, 0.5];

/// The pixels of a `[H, W]` network input that see inside the camera's field of view and are
/// not padding, `[H, W]` bool. The input is the camera image padded by `frame.padding` and
/// scaled to `size` (as the calibrated offsets assume); fisheye models: the ray is within
/// `fov / 2` of the optical axis ([`crate::data::views::max_ray_angle`]); perspective: every
/// pixel of the image.
pub fn field_of_view_mask(camera: &Camera, frame: &InputFrame, size: [i64; 2]) -> Tensor {
    let [cw, ch] = camera.size();
    let s = [
        size[1] as f64 / (cw + frame.padding[0]) as f64,
        size[0] as f64 / (ch + frame.padding[1]) as f64,
    ];
    let scaled = camera.rescaled(s, frame.convention);
    let half_fov = crate::data::views::max_ray_angle(camera);
    let (h, w) = (size[0] as usize, size[1] as usize);
    let mut valid = vec![false; h * w];
    for v in 0..h {
        for u in 0..w {
            let inside =
                (u as f64 + 0.5) <= cw as f64 * s[0] && (v as f64 + 0.5) <= ch as f64 * s[1];
            let sees = match (half_fov, scaled.unproject([u as f64, v as f64])) {
                (_, None) => false,
                (None, Some(_)) => true,
                (Some(hf), Some(ray)) => ray[2].clamp(-1.0, 1.0).acos() <= hf,
            };
            valid[v * w + u] = inside && sees;
        }
    }
    Tensor::from_slice(&valid).view([size[0], size[1]])
}

/// Generates `n` toy samples of `size` `[H, W]` from `seed`; `valid` (`[H, W]` bool, e.g. from
/// [`field_of_view_mask`]) limits where the image is. Returns `(image [N,3,H,W] f32, depth
/// [N,1,H,W] f32, labels [N,H,W] i64, mask [N,1,H,W] bool, ids)`.
pub fn toy_samples(
    n: usize,
    size: [i64; 2],
    seed: u64,
    valid: Option<&Tensor>,
) -> Result<(Tensor, Tensor, Tensor, Tensor, Vec<String>)> {
    if n == 0 || size[0] < 2 || size[1] < 2 {
        return Err(Error::InvalidArgument(format!(
            "toy data: need samples > 0 and a size of at least 2x2, got {n} samples of {size:?}"
        )));
    }
    let (h, w) = (size[0] as usize, size[1] as usize);
    let valid: Vec<bool> = match valid {
        Some(v) => Vec::<bool>::try_from(v.flatten(0, -1))?,
        None => vec![true; h * w],
    };
    let mut rgb = vec![0f32; n * 3 * h * w];
    let mut depth = vec![0f32; n * h * w];
    let mut labels = vec![IGNORE_LABEL; n * h * w];
    let mut mask = vec![false; n * h * w];
    for i in 0..n {
        let mut rng = SplitMix64::new(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (i as u64 + 1));
        // Region 0 is the background; then 3..=6 shapes, later ones on top.
        let n_shapes = 3 + rng.below(4);
        let mut regions = Vec::with_capacity(n_shapes + 1);
        let pick = |rng: &mut SplitMix64| {
            let class = if rng.below(10) == 0 {
                None
            } else {
                Some(rng.below(NUM_CLASSES))
            };
            let shade = 0.55 + 0.45 * rng.next_f64() as f32;
            (class, shade)
        };
        regions.push((pick(&mut rng), 0usize, [0.0f64; 4]));
        for _ in 0..n_shapes {
            let c = pick(&mut rng);
            let kind = 1 + rng.below(2); // 1 rectangle, 2 disc
            let cx = rng.next_f64() * w as f64;
            let cy = rng.next_f64() * h as f64;
            let rx = (0.1 + 0.3 * rng.next_f64()) * w as f64;
            let ry = (0.1 + 0.3 * rng.next_f64()) * h as f64;
            regions.push((c, kind, [cx, cy, rx, ry]));
        }
        for y in 0..h {
            let light = 0.08 * (2.0 * y as f32 / (h - 1) as f32 - 1.0);
            for x in 0..w {
                let p = y * w + x;
                if !valid[p] {
                    continue;
                }
                let mut region = &regions[0];
                for r in &regions[1..] {
                    let [cx, cy, rx, ry] = r.2;
                    let (dx, dy) = ((x as f64 - cx) / rx, (y as f64 - cy) / ry);
                    let inside = match r.1 {
                        1 => dx.abs() <= 1.0 && dy.abs() <= 1.0,
                        _ => dx * dx + dy * dy <= 1.0,
                    };
                    if inside {
                        region = r;
                    }
                }
                let ((class, shade), _, _) = *region;
                let base = class.map_or(UNKNOWN_COLOUR, |c| TOY_COLOURS[c]);
                let mut lum = 0.0;
                for c in 0..3 {
                    let v = (base[c] * shade + light).clamp(0.0, 1.0);
                    rgb[((i * 3 + c) * h + y) * w + x] = v;
                    lum += v / 3.0;
                }
                depth[i * h * w + p] = 1.0 + 8.0 * (1.0 - lum);
                labels[i * h * w + p] = class.map_or(IGNORE_LABEL, |c| c as i64);
                mask[i * h * w + p] = true;
            }
        }
    }
    let n = n as i64;
    let cpu = Device::Cpu;
    Ok((
        Tensor::from_slice(&rgb).view([n, 3, size[0], size[1]]),
        Tensor::from_slice(&depth).view([n, 1, size[0], size[1]]),
        Tensor::from_slice(&labels).view([n, size[0], size[1]]),
        Tensor::from_slice(&mask)
            .view([n, 1, size[0], size[1]])
            .to_device(cpu),
        (0..n).map(|i| format!("toy{seed:x}-{i:04}")).collect(),
    ))
}

/// A [`MemorySource`] of [`toy_samples`].
pub fn toy_source(
    n: usize,
    size: [i64; 2],
    content_seed: u64,
    valid: Option<&Tensor>,
    batch_size: usize,
    shuffle: Option<u64>,
) -> Result<MemorySource> {
    let (image, depth, labels, mask, ids) = toy_samples(n, size, content_seed, valid)?;
    debug_assert_eq!(image.kind(), Kind::Float);
    MemorySource::new(image, depth, labels, mask, ids, batch_size, shuffle)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::BatchSource;

    #[test]
    fn samples_follow_the_data_contract_and_the_seed() {
        let cam = crate::camera::shipped("f195");
        // F195 (1080x960) padded by 8 px on the right, at 1/8: 136x120.
        let frame = InputFrame {
            padding: [8, 0],
            ..Default::default()
        };
        let fov = field_of_view_mask(&cam, &frame, [120, 136]);
        // The principal point sees the axis; the corners and the padding column do not.
        assert!(bool::try_from(fov.get(60).get(67)).unwrap());
        assert!(!bool::try_from(fov.get(0).get(0)).unwrap());
        assert!(!bool::try_from(fov.get(60).get(135)).unwrap());
        let s = toy_source(5, [120, 136], 3, Some(&fov), 2, Some(1)).unwrap();
        let b = s.batches(0, 0).next().unwrap().unwrap();
        assert_eq!(b.image.size(), [2, 3, 120, 136]);
        let m = b.mask.squeeze_dim(1);
        // Outside the mask: zeros and IGNORE_LABEL; inside: depth in [1, 9].
        let outside = m.logical_not();
        assert_eq!(
            b.labels
                .masked_select(&outside)
                .ne(IGNORE_LABEL)
                .sum(Kind::Int64)
                .int64_value(&[]),
            0
        );
        assert_eq!(
            b.depth
                .masked_select(&b.mask.logical_not())
                .abs()
                .sum(Kind::Float)
                .double_value(&[]),
            0.0
        );
        let d = b.depth.masked_select(&b.mask);
        assert!(d.min().double_value(&[]) >= 1.0 && d.max().double_value(&[]) <= 9.0);
        // Same seed, same pixels; another seed, other pixels.
        let a = toy_samples(2, [16, 16], 3, None).unwrap().0;
        assert!(a.equal(&toy_samples(2, [16, 16], 3, None).unwrap().0));
        assert!(!a.equal(&toy_samples(2, [16, 16], 4, None).unwrap().0));
    }
}
