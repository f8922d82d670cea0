//! Procedural appearance: value noise, per-class materials with textures, and the shading model.
//!
//! Colours are linear RGB in `[0, 1]` until [`tone_map`] turns radiance into 8-bit sRGB-like
//! values. Textures are evaluated from the hit point in the primitive's frame
//! ([`super::geometry::Hit::local`]), on two surface coordinates `(s, t)` chosen by the face's
//! normal axis: a horizontal face uses `(x, z)`, a face across x uses `(z, y)`, a face across z
//! uses `(x, y)`; metres throughout, y down.
//!
//! Shading (Lambert with point lights, inverse-square-like falloff, hemispherical ambient):
//!
//! ```text
//! L = albedo * (A (0.75 + 0.25 up) + sum_k V_k I_k max(0, n . l_k) / (1 + (d_k / R)^2)) + E
//! ```
//!
//! `up = -n_y` (1 on the floor, -1 on the ceiling), `l_k` the unit vector to light `k` at
//! distance `d_k`, `V_k` its visibility (shadow ray), `R` = [`FALLOFF_M`], `E` the emission of
//! windows and light panels. The `n . l` term and the falloff make brightness depend on surface
//! orientation and position, which is what makes depth and layout learnable from RGB.

use super::geometry::Hit;
use crate::data::rng::{hash, Rng};

/// Distance at which a light's contribution halves, in metres.
pub const FALLOFF_M: f64 = 2.5;

/// A linear-RGB colour.
pub type Rgb = [f32; 3];

/// An 8-bit sRGB colour to linear RGB (gamma 2.2 approximation).
pub fn srgb(r: u8, g: u8, b: u8) -> Rgb {
    [r, g, b].map(|c| (c as f32 / 255.0).powf(2.2))
}

/// An 8-bit sRGB colour written `0xRRGGBB` to linear RGB ([`srgb`]): palettes are tables of these.
pub fn hex(c: u32) -> Rgb {
    srgb((c >> 16) as u8, (c >> 8) as u8, c as u8)
}

/// A colour of `palette` (`0xRRGGBB` values, [`hex`]) drawn uniformly by `rng`.
pub fn pick_srgb(rng: &mut Rng, palette: &[u32]) -> Rgb {
    hex(*rng.pick(palette))
}

/// `a + (b - a) w`, componentwise.
pub fn mix(a: Rgb, b: Rgb, w: f32) -> Rgb {
    [0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * w)
}

/// `c * s`, componentwise.
pub fn tint(c: Rgb, s: f32) -> Rgb {
    c.map(|v| v * s)
}

/// A colour with its brightness scaled by `1 + amount * N(0,1)` (clamped to `[0.5, 1.5]`) and
/// each channel nudged by `amount / 3 * N(0,1)`: the instance-to-instance variation of a class.
pub fn vary(c: Rgb, rng: &mut Rng, amount: f32) -> Rgb {
    let b = (1.0 + amount * rng.normal() as f32).clamp(0.5, 1.5);
    c.map(|v| (v * b * (1.0 + amount / 3.0 * rng.normal() as f32)).clamp(0.0, 1.0))
}

/// Uniform in `[0, 1)` from the hash of integer lattice coordinates.
fn lattice(seed: u64, i: i64, j: i64, k: i64) -> f32 {
    (hash(seed, &[i as u64, j as u64, k as u64]) >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

/// Value noise in `[0, 1]`: lattice values at integer points, trilinear with smoothstep weights.
pub fn value_noise(seed: u64, p: [f64; 3]) -> f32 {
    let f = p.map(|v| v.floor());
    let i = f.map(|v| v as i64);
    let w = [0, 1, 2].map(|a| {
        let x = (p[a] - f[a]) as f32;
        x * x * (3.0 - 2.0 * x)
    });
    let mut acc = 0.0;
    for c in 0..8 {
        let (dx, dy, dz) = ((c & 1) as i64, ((c >> 1) & 1) as i64, (c >> 2) as i64);
        let wx = if dx == 1 { w[0] } else { 1.0 - w[0] };
        let wy = if dy == 1 { w[1] } else { 1.0 - w[1] };
        let wz = if dz == 1 { w[2] } else { 1.0 - w[2] };
        acc += wx * wy * wz * lattice(seed, i[0] + dx, i[1] + dy, i[2] + dz);
    }
    acc
}

/// Two octaves of value noise at frequency `freq` (cycles per metre), in `[0, 1]`.
pub fn fbm(seed: u64, p: [f64; 3], freq: f64) -> f32 {
    let q = p.map(|v| v * freq);
    let a = value_noise(seed, q);
    let b = value_noise(seed ^ 0x5555, q.map(|v| v * 2.03 + 17.0));
    (a * 0.67 + b * 0.33).clamp(0.0, 1.0)
}

/// The fraction of the interval `[x - fp / 2, x + fp / 2]` covered by the lines
/// `[k period, k period + width]` (a pulse train box-filtered over a pixel footprint `fp`):
/// with `C(y) = floor(y / P) w + min(y - floor(y / P) P, w)` the covered length below `y`,
/// the coverage is `(C(x + fp / 2) - C(x - fp / 2)) / fp`; a point sample when `fp` is tiny.
pub fn line_coverage(x: f64, period: f64, width: f64, fp: f64) -> f32 {
    let covered = |y: f64| {
        let k = (y / period).floor();
        k * width + (y - k * period).min(width)
    };
    if fp < 1e-9 {
        let r = x - (x / period).floor() * period;
        return if r < width { 1.0 } else { 0.0 };
    }
    ((covered(x + fp / 2.0) - covered(x - fp / 2.0)) / fp).clamp(0.0, 1.0) as f32
}

/// Coverage of a grid of lines from the coverages along its two directions (independent).
fn grid_coverage(a: f32, b: f32) -> f32 {
    1.0 - (1.0 - a) * (1.0 - b)
}

/// How a material varies over its surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pattern {
    /// Plain colour with blotches of relative amplitude `amp` at `freq` cycles per metre
    /// (paint, plaster, plastic, metal).
    Plain {
        /// Cycles per metre.
        freq: f32,
        /// Relative amplitude.
        amp: f32,
    },
    /// Square tiles of `size` metres with `grout` metres of `alt` between them; each tile's
    /// brightness is jittered by `jitter`.
    Tiles {
        /// Tile period, metres.
        size: f32,
        /// Grout width, metres.
        grout: f32,
        /// Relative brightness jitter per tile.
        jitter: f32,
    },
    /// Planks `width` metres wide and `length` long along s, with a tone per plank and grain.
    Planks {
        /// Plank width (across t), metres.
        width: f32,
        /// Plank length (along s), metres.
        length: f32,
    },
    /// Fine isotropic noise (carpet, fabric).
    Fabric {
        /// Cycles per metre.
        freq: f32,
        /// Relative amplitude.
        amp: f32,
    },
    /// Running-bond concrete blocks (0.4 x 0.2 m, as the painted block walls of university
    /// buildings) in `base` with `alt` mortar.
    Blocks,
    /// Books standing in a shelf compartment of half height `half_height` (local y): slots of
    /// 3-5 cm along local x with colours from a palette, `alt` behind and above them.
    Books {
        /// Half height of the compartment (local y), metres.
        half_height: f32,
    },
    /// A board surface with strokes of `alt` along lines of text (whiteboard, blackboard).
    Board,
    /// A window of half size `half` (local x, y): emissive sky through `panes` with mullions and
    /// a border of `alt`.
    Window {
        /// Half size (local x, y), metres.
        half: [f32; 2],
        /// Panes across (x) and down (y).
        panes: [u8; 2],
    },
    /// An emissive ceiling light panel of half size `half` (local x, z) with an `alt` rim.
    Light {
        /// Half size (local x, z), metres.
        half: [f32; 2],
    },
    /// A monitor screen: dark glass with a faint blue glow.
    Screen,
}

/// A surface material: two colours and a pattern; `seed` decorrelates its noise from others.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    /// Main colour.
    pub base: Rgb,
    /// Second colour (grout, mortar, frame, ink...).
    pub alt: Rgb,
    /// How the two vary over the surface.
    pub pattern: Pattern,
    /// Seed of the material's noise.
    pub seed: u64,
}

/// What a surface point looks like: its diffuse albedo and its own emission.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surface {
    /// Diffuse reflectance, linear RGB in `[0, 1]`.
    pub albedo: Rgb,
    /// Emitted radiance (windows, light panels, screens).
    pub emission: Rgb,
}

impl Material {
    /// A material without a pattern beyond gentle blotches.
    pub fn plain(base: Rgb, seed: u64) -> Self {
        Material {
            base,
            alt: base,
            pattern: Pattern::Plain {
                freq: 1.5,
                amp: 0.08,
            },
            seed,
        }
    }

    /// The surface at a hit (see the module docs for the `(s, t)` coordinates). `footprint`
    /// is the width of the pixel on the surface, metres: thin periodic lines (grout, mortar,
    /// plank gaps, mullions, strokes) are box-filtered with [`line_coverage`] over twice that
    /// (the usual margin for a texture that view synthesis resamples again), so distant and
    /// grazing textures average out instead of aliasing into moire.
    pub fn surface(&self, hit: &Hit, footprint: f64) -> Surface {
        let fp = 2.0 * footprint;
        // Textures with a grid (tiles, planks, bricks) are shifted by a per-material offset,
        // or every grout line through the origin would pass exactly under the camera.
        let off = |k: u64| (hash(self.seed, &[k]) >> 11) as f64 / (1u64 << 53) as f64 * 8.0;
        let p = match self.pattern {
            Pattern::Tiles { .. } | Pattern::Planks { .. } | Pattern::Blocks => [
                hit.local[0] + off(0),
                hit.local[1] + off(1),
                hit.local[2] + off(2),
            ],
            _ => hit.local,
        };
        let (s, t) = match hit.axis {
            1 => (p[0], p[2]),
            0 => (p[2], p[1]),
            _ => (p[0], p[1]),
        };
        match self.pattern {
            Pattern::Plain { freq, amp } => {
                let n = fbm(self.seed, p, freq as f64) - 0.5;
                dull(tint(self.base, 1.0 + 2.0 * amp * n))
            }
            Pattern::Fabric { freq, amp } => {
                let n = value_noise(self.seed, p.map(|v| v * freq as f64)) - 0.5;
                let m = fbm(self.seed ^ 1, p, 2.0) - 0.5;
                dull(tint(self.base, 1.0 + 2.0 * amp * n + 0.15 * m))
            }
            Pattern::Tiles {
                size,
                grout,
                jitter,
            } => self.tiles(p, [s, t], fp, [size as f64, grout as f64], jitter),
            Pattern::Planks { width, length } => {
                self.planks([s, t], fp, width as f64, length as f64)
            }
            Pattern::Blocks => self.blocks([s, t], fp),
            Pattern::Books { half_height } => self.books(p, s, half_height as f64),
            Pattern::Board => self.board(p, [s, t], fp),
            Pattern::Window { half, panes } => self.window(p, fp, half, panes),
            Pattern::Light { half } => {
                let rim = 0.03;
                let (lx, lz) = (p[0], p[2]);
                if half[0] as f64 - lx.abs() < rim || half[1] as f64 - lz.abs() < rim {
                    return dull(self.alt);
                }
                Surface {
                    albedo: [0.1; 3],
                    emission: tint(self.base, 3.0),
                }
            }
            Pattern::Screen => {
                let glow = 0.03 + 0.04 * fbm(self.seed, p, 4.0);
                Surface {
                    albedo: [0.03; 3],
                    emission: [glow * 0.6, glow * 0.8, glow * 1.4],
                }
            }
        }
    }

    /// [`Pattern::Tiles`] at `p`, surface coordinates `(s, t)`: `[size, grout]` in metres.
    fn tiles(
        &self,
        p: [f64; 3],
        [s, t]: [f64; 2],
        fp: f64,
        [size, grout]: [f64; 2],
        jitter: f32,
    ) -> Surface {
        let seed = self.seed;
        let (fs, ft) = ((s / size).floor(), (t / size).floor());
        let cov = grid_coverage(
            line_coverage(s, size, grout, fp),
            line_coverage(t, size, grout, fp),
        );
        let tone = lattice(seed, fs as i64, ft as i64, 7) - 0.5;
        let n = fbm(seed, p, 6.0) - 0.5;
        let tile = tint(self.base, 1.0 + 2.0 * jitter * tone + 0.12 * n);
        dull(mix(tile, self.alt, cov))
    }

    /// [`Pattern::Planks`] at surface coordinates `(s, t)`.
    fn planks(&self, [s, t]: [f64; 2], fp: f64, width: f64, length: f64) -> Surface {
        let seed = self.seed;
        let row = (t / width).floor();
        // Staggered plank ends: each row shifts by a random fraction of a length.
        let shift = lattice(seed, row as i64, 0, 3) as f64 * length;
        let col = ((s + shift) / length).floor();
        let gap = grid_coverage(
            line_coverage(t, width, 0.004, fp),
            line_coverage(s + shift, length, 0.004, fp),
        );
        let tone = lattice(seed, row as i64, col as i64, 5) - 0.5;
        // Grain: noise stretched along the plank.
        let g = value_noise(seed ^ 9, [s * 3.0, t * 60.0, row]) - 0.5;
        let wood = mix(
            tint(self.base, 1.0 + 0.35 * tone),
            self.alt,
            (0.5 + g).clamp(0.0, 1.0) * 0.45,
        );
        dull(mix(wood, tint(self.base, 0.55), gap))
    }

    /// [`Pattern::Blocks`] at surface coordinates `(s, t)`.
    fn blocks(&self, [s, t]: [f64; 2], fp: f64) -> Surface {
        let (bw, bh, m) = (0.4, 0.2, 0.012);
        let course = (t / bh).floor();
        let off = if course as i64 % 2 == 0 {
            0.0
        } else {
            bw / 2.0
        };
        let col = ((s + off) / bw).floor();
        let cov = grid_coverage(
            line_coverage(s + off, bw, m, fp),
            line_coverage(t, bh, m, fp),
        );
        let tone = lattice(self.seed, col as i64, course as i64, 11) - 0.5;
        dull(mix(tint(self.base, 1.0 + 0.12 * tone), self.alt, cov))
    }

    /// [`Pattern::Books`] at `p` (local y down), surface coordinate `s` along the shelf.
    fn books(&self, p: [f64; 3], s: f64, half_height: f64) -> Surface {
        let seed = self.seed;
        let slot_w = 0.04;
        let slot = ((s + 10.0) / slot_w).floor() as i64;
        let r = lattice(seed, slot, 0, 13);
        if r < 0.08 {
            return dull(self.alt); // a gap in the row
        }
        let height = 0.55 + 0.4 * lattice(seed, slot, 1, 13) as f64;
        // Local y grows downwards; books stand on the compartment floor at +half_height.
        let top = half_height * (1.0 - 2.0 * height);
        if p[1] < top {
            return dull(self.alt);
        }
        let palette = [
            0x962823, 0x233C78, 0x28643C, 0xC8B48C, 0x1E1E1E, 0xD27828, 0xE6E6DC, 0x64285A,
        ];
        let i = (lattice(seed, slot, 2, 13) * palette.len() as f32) as usize % palette.len();
        let c = hex(palette[i]);
        // A spine band.
        let band = (p[1] - top) / (half_height * 2.0 * height);
        let spine = if (0.15..0.2).contains(&band) {
            0.6
        } else {
            1.0
        };
        dull(tint(c, spine * (0.8 + 0.4 * lattice(seed, slot, 3, 13))))
    }

    /// [`Pattern::Board`] at `p`, surface coordinates `(s, t)`.
    fn board(&self, p: [f64; 3], [s, t]: [f64; 2], fp: f64) -> Surface {
        let seed = self.seed;
        let line_h = 0.09;
        let row = (t / line_h).floor();
        let y = t - row * line_h;
        let wiggle = 0.012 * (s * 55.0 + row).sin() * (s * 13.0).cos();
        let written = lattice(seed, row as i64, 0, 17) < 0.55
            && value_noise(seed, [s * 6.0, row, 0.0]) > 0.45;
        // A 1 cm stroke centred in its line, filtered over the footprint.
        let ink = if written {
            line_coverage(y - line_h / 2.0 - wiggle + 0.005, line_h, 0.01, fp)
        } else {
            0.0
        };
        let smudge = fbm(seed ^ 3, p, 3.0) - 0.5;
        dull(mix(tint(self.base, 1.0 + 0.1 * smudge), self.alt, ink))
    }

    /// [`Pattern::Window`] at `p` (local x, y).
    fn window(&self, p: [f64; 3], fp: f64, half: [f32; 2], panes: [u8; 2]) -> Surface {
        let (lx, ly) = (p[0], p[1]);
        // Frame bars 6 cm wide centred on the pane edges (so 3 cm of border): lines
        // at -h + k 2h / n for k = 0..=n, filtered over the footprint.
        let bar = 0.06;
        let (hx, hy) = (half[0] as f64, half[1] as f64);
        let bars =
            |v: f64, h: f64, n: u8| line_coverage(v + h + bar / 2.0, 2.0 * h / n as f64, bar, fp);
        let cov = grid_coverage(bars(lx, hx, panes[0]), bars(ly, hy, panes[1]));
        // Sky: brighter and bluer towards the top (local y grows downwards), clouds.
        let up = (0.5 - ly / (2.0 * hy)) as f32;
        let cloud = fbm(self.seed, p, 1.2);
        let sky = mix(srgb(200, 215, 230), srgb(120, 160, 215), up);
        let c = mix(sky, [1.0; 3], (cloud - 0.45).max(0.0) * 1.5);
        Surface {
            albedo: mix([0.04; 3], self.alt, cov),
            emission: tint(c, 1.6 * (1.0 - cov)),
        }
    }
}

/// A surface that only reflects.
fn dull(albedo: Rgb) -> Surface {
    Surface {
        albedo,
        emission: [0.0; 3],
    }
}

/// Radiance to an 8-bit sRGB-like value: `255 (1 - exp(-exposure L))^(1/2.2) + dither`, with a
/// dither in `[-1, 1]` levels standing in for sensor noise.
pub fn tone_map(l: Rgb, exposure: f32, dither: f32) -> [u8; 3] {
    l.map(|v| {
        let x = 1.0 - (-exposure * v.max(0.0)).exp();
        (255.0 * x.powf(1.0 / 2.2) + dither)
            .round()
            .clamp(0.0, 255.0) as u8
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_noise_is_bounded_continuous_and_seeded() {
        let mut max_step: f32 = 0.0;
        let mut prev = value_noise(1, [0.0, 0.3, 0.7]);
        for i in 1..2000 {
            let x = i as f64 * 0.001;
            let v = value_noise(1, [x, 0.3, 0.7]);
            assert!((0.0..=1.0).contains(&v));
            max_step = max_step.max((v - prev).abs());
            prev = v;
        }
        // Smoothstep interpolation: slope <= 1.5 per lattice cell, so a 1e-3 step moves < 2e-3.
        assert!(max_step < 2e-3, "{max_step}");
        assert_ne!(value_noise(1, [0.5; 3]), value_noise(2, [0.5; 3]));
    }

    #[test]
    fn line_coverage_is_the_box_filtered_pulse_train() {
        // Point samples.
        assert_eq!(line_coverage(0.05, 1.0, 0.1, 0.0), 1.0);
        assert_eq!(line_coverage(0.5, 1.0, 0.1, 0.0), 0.0);
        // A footprint of several periods sees the duty cycle width / period.
        let c = line_coverage(0.37, 1.0, 0.1, 10.0);
        assert!((c - 0.1).abs() < 1e-6, "{c}");
        // Half of a line inside a footprint of one line width.
        let c = line_coverage(0.1, 1.0, 0.1, 0.1);
        assert!((c - 0.5).abs() < 1e-6, "{c}");
        // Negative coordinates tile the same way.
        let c = line_coverage(-0.95, 1.0, 0.1, 0.0);
        assert_eq!(c, 1.0);
    }

    #[test]
    fn tone_map_is_monotonic_and_saturates() {
        let a = tone_map([0.1; 3], 1.0, 0.0);
        let b = tone_map([0.5; 3], 1.0, 0.0);
        assert!(a[0] < b[0]);
        assert_eq!(tone_map([1e6; 3], 1.0, 0.0), [255; 3]);
        assert_eq!(tone_map([0.0; 3], 1.0, 0.0), [0; 3]);
    }
}
