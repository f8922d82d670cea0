//! Equirectangular panoramas (RGB, metric depth, labels) and the procedural indoor scenes that
//! render them.
//!
//! # Conventions
//!
//! - World axes as the camera module: x right, y **down**, z forward; metres; the panorama's
//!   centre of projection is the origin.
//! - A `width x height` panorama (`width = 2 height`) maps pixel `(u, v)` (column, row; the
//!   centre of the top-left pixel at `(0, 0)`, as everywhere in the crate) to
//!
//!   ```text
//!   lon = 2 pi (u + 0.5) / width - pi        in (-pi, pi), 0 at the image centre, + to the right
//!   lat = pi / 2 - pi (v + 0.5) / height     in (-pi/2, pi/2), + up (top row looks up)
//!   dir = (cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon))
//!   ```
//!
//!   so the centre column looks along +z, a quarter to the right along +x, the top row up (-y).
//!   The inverse is `lon = atan2(x, z)`, `lat = asin(-y)` ([`Panorama::pixel_of`]).
//! - `depth` is the distance from the centre of projection along the ray (not z), in metres;
//!   `0` marks a missing value (as in the data set contract). `labels` are class ids in
//!   [`crate::data::CLASSES`] order or [`crate::data::UNKNOWN_PNG_LABEL`].
//!
//! # Procedural scenes
//!
//! [`render_procedural`] builds [`scene::Scene::generate`]`(seed)` (rooms, furniture, lights;
//! see [`scene`]) and casts one ray per pixel through its centre (analytic intersections, see
//! [`geometry`]), shading with [`appearance`]. Rows are rendered in parallel with rayon; the
//! result depends only on the seed and the size (not on the thread count).

pub mod appearance;
pub mod geometry;
pub mod scene;

use std::f64::consts::{PI, TAU};

use rayon::prelude::*;

use crate::data::rng::hash;
use crate::data::UNKNOWN_PNG_LABEL;
use crate::error::{Error, Result};
use geometry::V3;
use scene::Scene;

/// One rendered pixel: RGB, depth, label.
type PanoPixel = ([u8; 3], f32, u8);

/// An equirectangular panorama with per-pixel colour, distance and class (row-major,
/// `height` rows of `width` pixels).
#[derive(Clone, Debug, PartialEq)]
pub struct Panorama {
    /// Width in pixels (`2 height`).
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// 8-bit RGB.
    pub rgb: Vec<[u8; 3]>,
    /// Distance from the centre, metres; 0 = missing.
    pub depth: Vec<f32>,
    /// Class ids in `CLASSES` order, `UNKNOWN_PNG_LABEL` for unknown.
    pub labels: Vec<u8>,
}

impl Panorama {
    /// Unit direction through the centre of pixel `(u, v)` (may be fractional) of a
    /// `width x height` panorama (formula in the module docs).
    pub fn direction(width: usize, height: usize, u: f64, v: f64) -> V3 {
        let lon = TAU * (u + 0.5) / width as f64 - PI;
        let lat = PI / 2.0 - PI * (v + 0.5) / height as f64;
        let (sl, cl) = lat.sin_cos();
        [cl * lon.sin(), -sl, cl * lon.cos()]
    }

    /// Continuous pixel coordinates `(u, v)` of a unit direction: the inverse of
    /// [`Panorama::direction`], `u` in `[-0.5, width - 0.5)`, `v` in `[-0.5, height - 0.5]`.
    pub fn pixel_of(&self, dir: V3) -> [f64; 2] {
        let lon = dir[0].atan2(dir[2]);
        let lat = (-dir[1]).clamp(-1.0, 1.0).asin();
        [
            (lon + PI) / TAU * self.width as f64 - 0.5,
            (PI / 2.0 - lat) / PI * self.height as f64 - 0.5,
        ]
    }

    /// Index of pixel `(col, row)` after wrapping: columns wrap around the seam, and a row
    /// beyond a pole continues on the other side of it (row `-1 - r` is row `r` half a turn
    /// away, likewise below the bottom), which is exact for an equirectangular image.
    pub fn wrap_index(&self, col: i64, row: i64) -> usize {
        let (w, h) = (self.width as i64, self.height as i64);
        let (mut c, mut r) = (col, row);
        if r < 0 {
            r = -1 - r;
            c += w / 2;
        } else if r >= h {
            r = 2 * h - 1 - r;
            c += w / 2;
        }
        let r = r.clamp(0, h - 1);
        (r * w + c.rem_euclid(w)) as usize
    }

    /// Bilinear RGB at continuous pixel coordinates (wrapping as [`Panorama::wrap_index`]), as
    /// floats in `[0, 255]`.
    pub fn bilinear_rgb(&self, px: [f64; 2]) -> [f32; 3] {
        let (fu, fv) = (px[0].floor(), px[1].floor());
        let (wu, wv) = ((px[0] - fu) as f32, (px[1] - fv) as f32);
        let (c0, r0) = (fu as i64, fv as i64);
        let mut out = [0.0f32; 3];
        for (dc, dr, w) in [
            (0, 0, (1.0 - wu) * (1.0 - wv)),
            (1, 0, wu * (1.0 - wv)),
            (0, 1, (1.0 - wu) * wv),
            (1, 1, wu * wv),
        ] {
            let p = self.rgb[self.wrap_index(c0 + dc, r0 + dr)];
            for k in 0..3 {
                out[k] += w * p[k] as f32;
            }
        }
        out
    }

    /// Index of the pixel nearest to continuous coordinates (for depth and labels).
    pub fn nearest_index(&self, px: [f64; 2]) -> usize {
        self.wrap_index(px[0].round() as i64, px[1].round() as i64)
    }

    /// Checks that the buffers match the size and the size is 2:1.
    pub fn check(&self) -> Result<()> {
        let n = self.width * self.height;
        if self.width != 2 * self.height || self.height == 0 {
            return Err(Error::InvalidArgument(format!(
                "panorama is {}x{}, expected width = 2 height > 0",
                self.width, self.height
            )));
        }
        if self.rgb.len() != n || self.depth.len() != n || self.labels.len() != n {
            return Err(Error::InvalidArgument(format!(
                "panorama buffers ({}, {}, {}) do not match {}x{}",
                self.rgb.len(),
                self.depth.len(),
                self.labels.len(),
                self.width,
                self.height
            )));
        }
        Ok(())
    }

    /// A panorama `factor` times smaller in each direction: RGB is the mean of each
    /// `factor x factor` block (anti-aliasing), depth and label are the block's pixel nearest
    /// to its centre (`(factor / 2, factor / 2)`, never blending across object edges).
    pub fn downsample(&self, factor: usize) -> Result<Panorama> {
        if factor == 0 || !self.width.is_multiple_of(factor) || !self.height.is_multiple_of(factor)
        {
            return Err(Error::InvalidArgument(format!(
                "cannot downsample a {}x{} panorama by {factor}",
                self.width, self.height
            )));
        }
        if factor == 1 {
            return Ok(self.clone());
        }
        let (w, h) = (self.width / factor, self.height / factor);
        let rows: Vec<Vec<PanoPixel>> = (0..h)
            .into_par_iter()
            .map(|r| {
                (0..w)
                    .map(|c| {
                        let mut acc = [0u32; 3];
                        for dr in 0..factor {
                            let row = (r * factor + dr) * self.width;
                            for dc in 0..factor {
                                let p = self.rgb[row + c * factor + dc];
                                for k in 0..3 {
                                    acc[k] += p[k] as u32;
                                }
                            }
                        }
                        let n = (factor * factor) as u32;
                        let centre =
                            (r * factor + factor / 2) * self.width + c * factor + factor / 2;
                        (
                            acc.map(|a| ((a + n / 2) / n) as u8),
                            self.depth[centre],
                            self.labels[centre],
                        )
                    })
                    .collect()
            })
            .collect();
        Ok(Panorama::from_pixels(w, h, rows.into_iter().flatten()))
    }

    /// A `width x height` panorama of `pixels` in row-major order.
    fn from_pixels(width: usize, height: usize, pixels: impl Iterator<Item = PanoPixel>) -> Self {
        let (rgb, depth, labels) = pixels.collect();
        Panorama {
            width,
            height,
            rgb,
            depth,
            labels,
        }
    }
}

/// Renders `scene` as a `2 height x height` panorama, one ray per pixel centre, rows in
/// parallel.
pub fn render(scene: &Scene, height: usize) -> Panorama {
    let width = 2 * height;
    let rows: Vec<Vec<PanoPixel>> = (0..height)
        .into_par_iter()
        .map(|v| {
            (0..width)
                .map(|u| {
                    let dir = Panorama::direction(width, height, u as f64, v as f64);
                    let s = scene.sample(dir, PI / height as f64);
                    let i = v * width + u;
                    // Dither in [-1, 1] levels, a function of the scene and the pixel only.
                    let d = (hash(scene.seed, &[i as u64]) >> 40) as f32 / (1u64 << 24) as f32;
                    let rgb = appearance::tone_map(s.radiance, scene.exposure, 2.0 * d - 1.0);
                    let label = if s.depth > 0.0 {
                        s.class
                    } else {
                        UNKNOWN_PNG_LABEL
                    };
                    (rgb, s.depth as f32, label)
                })
                .collect()
        })
        .collect();
    Panorama::from_pixels(width, height, rows.into_iter().flatten())
}

/// Seed of procedural panorama `index` of a data set with seed `seed`.
pub fn panorama_seed(seed: u64, index: u64) -> u64 {
    hash(seed, &[crate::data::rng::tag("panorama"), index])
}

/// The procedural panorama `index` of the data set seeded `seed`, `2 height x height` pixels.
pub fn render_procedural(seed: u64, index: u64, height: usize) -> (Scene, Panorama) {
    let scene = Scene::generate(panorama_seed(seed, index));
    let pano = render(&scene, height);
    (scene, pano)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::NUM_CLASSES;

    #[test]
    fn direction_and_pixel_of_are_inverse() {
        let p = Panorama {
            width: 64,
            height: 32,
            rgb: vec![],
            depth: vec![],
            labels: vec![],
        };
        for (u, v) in [(0.0, 0.0), (31.5, 15.5), (63.0, 31.0), (10.25, 3.75)] {
            let d = Panorama::direction(64, 32, u, v);
            let px = p.pixel_of(d);
            assert!(
                (px[0] - u).abs() < 1e-9 && (px[1] - v).abs() < 1e-9,
                "{u} {v} {px:?}"
            );
        }
        // Axes: the centre looks along +z, a quarter turn right along +x, the top up (-y).
        let c = Panorama::direction(64, 32, 31.5, 15.5);
        assert!((c[2] - 1.0).abs() < 1e-12);
        let r = Panorama::direction(64, 32, 47.5, 15.5);
        assert!((r[0] - 1.0).abs() < 1e-12);
        assert!(Panorama::direction(64, 32, 31.5, 0.0)[1] < -0.99);
    }

    #[test]
    fn wrap_crosses_the_seam_and_the_poles() {
        let p = Panorama {
            width: 8,
            height: 4,
            rgb: vec![[0; 3]; 32],
            depth: vec![0.0; 32],
            labels: vec![0; 32],
        };
        assert_eq!(p.wrap_index(-1, 0), 7);
        assert_eq!(p.wrap_index(8, 1), 8);
        // Above the top row at column 1: row 0, column 1 + 4.
        assert_eq!(p.wrap_index(1, -1), 5);
        // Below the bottom row at column 6: row 3, column (6 + 4) mod 8 = 2.
        assert_eq!(p.wrap_index(6, 4), 3 * 8 + 2);
    }

    #[test]
    fn same_seed_same_bytes_other_seed_differs() {
        let (_, a) = render_procedural(11, 3, 24);
        let (_, b) = render_procedural(11, 3, 24);
        assert_eq!(a, b);
        let (_, c) = render_procedural(11, 4, 24);
        assert_ne!(a.rgb, c.rgb);
        let (_, d) = render_procedural(12, 3, 24);
        assert_ne!(a.rgb, d.rgb);
    }

    #[test]
    fn depth_is_positive_and_straight_down_meets_the_floor() {
        for index in 0..12 {
            let (scene, pano) = render_procedural(5, index, 32);
            assert!(pano.depth.iter().all(|&d| d > 0.0 && d < 40.0), "{index}");
            let h = scene.camera_height;
            // The ray straight down hits the floor at exactly the camera height.
            let down = scene.sample([0.0, 1.0, 0.0], 0.0);
            assert_eq!(down.class, scene::class::FLOOR, "{index}");
            assert!(
                (down.depth - h).abs() < 1e-12,
                "{index}: {} vs {h}",
                down.depth
            );
            // The bottom row's centres are pi / (2 height) above the nadir: depth h / cos.
            let v = pano.height - 1;
            let lat_off = std::f64::consts::PI * 0.5 / pano.height as f64;
            for u in 0..pano.width {
                let i = v * pano.width + u;
                assert_eq!(pano.labels[i], scene::class::FLOOR, "{index} {u}");
                let expect = h / lat_off.cos();
                assert!(
                    (pano.depth[i] as f64 - expect).abs() < 1e-5,
                    "{index}: {} vs {expect}",
                    pano.depth[i]
                );
            }
            // Straight up is the ceiling (or a beam / light panel hung from it).
            let up = scene.sample([0.0, -1.0, 0.0], 0.0);
            let room_top = scene.room_height - h;
            assert!(
                up.depth <= room_top + 1e-9 && up.depth > room_top - 0.7,
                "{index}"
            );
        }
    }

    #[test]
    fn labels_cover_many_classes() {
        let mut seen = [0usize; NUM_CLASSES];
        for index in 0..16 {
            let (_, pano) = render_procedural(1, index, 48);
            for &l in &pano.labels {
                assert!((l as usize) < NUM_CLASSES, "label {l}");
                seen[l as usize] += 1;
            }
        }
        let present = seen.iter().filter(|&&c| c > 0).count();
        // Every class appears somewhere in 16 rooms.
        assert_eq!(present, NUM_CLASSES, "{seen:?}");
    }

    #[test]
    fn downsample_averages_rgb_and_keeps_centre_labels() {
        let (_, p) = render_procedural(2, 0, 32);
        let d = p.downsample(4).unwrap();
        assert_eq!((d.width, d.height), (16, 8));
        let i = 3 * 16 + 5;
        let centre = (3 * 4 + 2) * 64 + 5 * 4 + 2;
        assert_eq!(d.labels[i], p.labels[centre]);
        assert_eq!(d.depth[i], p.depth[centre]);
        let mean: u32 = (0..4)
            .flat_map(|r| (0..4).map(move |c| (r, c)))
            .map(|(r, c)| p.rgb[(12 + r) * 64 + 20 + c][0] as u32)
            .sum();
        assert_eq!(d.rgb[i][0] as u32, (mean + 8) / 16);
        assert!(p.downsample(3).is_err());
    }
}
