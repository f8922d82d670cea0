//! Where things go: floor-plan footprints ([`Obb`]) and placement frames ([`Frame`]); the
//! reservations that keep furniture off each other, the doorways and the camera, and off each
//! other on the walls.

use super::{Builder, WallSeg, CAMERA_CLEARANCE_M};
use crate::data::rng::Rng;

/// A floor-plan footprint: a rectangle of half sizes `h` turned by `yaw` around `c` (x, z).
#[derive(Clone, Copy, Debug)]
pub(super) struct Obb {
    pub(super) c: [f64; 2],
    pub(super) h: [f64; 2],
    pub(super) yaw: f64,
}

impl Obb {
    /// Local axes in (x, z): local x -> (cos, -sin), local z -> (sin, cos).
    pub(super) fn axes(&self) -> [[f64; 2]; 2] {
        let (s, c) = self.yaw.sin_cos();
        [[c, -s], [s, c]]
    }
    pub(super) fn corners(&self) -> [[f64; 2]; 4] {
        let [ax, az] = self.axes();
        let mut out = [[0.0; 2]; 4];
        for (k, (sx, sz)) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            .into_iter()
            .enumerate()
        {
            out[k] = [
                self.c[0] + sx * self.h[0] * ax[0] + sz * self.h[1] * az[0],
                self.c[1] + sx * self.h[0] * ax[1] + sz * self.h[1] * az[1],
            ];
        }
        out
    }
    pub(super) fn grown(&self, m: f64) -> Obb {
        Obb {
            h: [self.h[0] + m, self.h[1] + m],
            ..*self
        }
    }
    /// Separating-axis test of two rectangles.
    pub(super) fn overlaps(&self, other: &Obb) -> bool {
        let (a, b) = (self.axes(), other.axes());
        let d = [other.c[0] - self.c[0], other.c[1] - self.c[1]];
        let proj = |v: [f64; 2], w: [f64; 2]| (v[0] * w[0] + v[1] * w[1]).abs();
        for axis in [a[0], a[1], b[0], b[1]] {
            let ra = self.h[0] * proj(a[0], axis) + self.h[1] * proj(a[1], axis);
            let rb = other.h[0] * proj(b[0], axis) + other.h[1] * proj(b[1], axis);
            if proj(d, axis) > ra + rb {
                return false;
            }
        }
        true
    }
    /// Distance from the origin (the camera) to the rectangle.
    pub(super) fn distance_to_origin(&self) -> f64 {
        let [ax, az] = self.axes();
        let v = [-self.c[0], -self.c[1]];
        let lx = v[0] * ax[0] + v[1] * ax[1];
        let lz = v[0] * az[0] + v[1] * az[1];
        let dx = (lx.abs() - self.h[0]).max(0.0);
        let dz = (lz.abs() - self.h[1]).max(0.0);
        dx.hypot(dz)
    }
}

/// A placement frame on the floor: origin `(x, z)` and yaw; local (x, z) -> world.
#[derive(Clone, Copy, Debug)]
pub(super) struct Frame {
    pub(super) x: f64,
    pub(super) z: f64,
    pub(super) yaw: f64,
}

impl Frame {
    pub(super) fn world(&self, lx: f64, lz: f64) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        [self.x + c * lx + s * lz, self.z - s * lx + c * lz]
    }
    pub(super) fn sub(&self, lx: f64, lz: f64, yaw: f64) -> Frame {
        let [x, z] = self.world(lx, lz);
        Frame {
            x,
            z,
            yaw: self.yaw + yaw,
        }
    }
}

/// A reserved stretch of wall: wall index, `[s0, s1]` along it, elevations `[e0, e1]`.
pub(super) type WallSpan = (usize, f64, f64, f64, f64);

impl Builder {
    pub(super) fn inside(&self, x: f64, z: f64) -> bool {
        self.rects.iter().any(|q| q.contains(x, z, -1e-9))
    }

    /// Whether the wall stretch is free.
    pub(super) fn wall_free(&self, w: usize, s: [f64; 2], e: [f64; 2]) -> bool {
        self.wall_used.iter().all(|&(wi, s0, s1, e0, e1)| {
            wi != w || s[1] <= s0 || s[0] >= s1 || e[1] <= e0 || e[0] >= e1
        })
    }

    /// Whether a floor rectangle fits: inside one plan rectangle, clear of the camera and of
    /// everything already placed.
    pub(super) fn floor_free(&self, obb: &Obb) -> bool {
        let corners = obb.corners();
        let inside = self
            .rects
            .iter()
            .any(|q| corners.iter().all(|c| q.contains(c[0], c[1], 0.0)));
        inside
            && obb.distance_to_origin() >= CAMERA_CLEARANCE_M
            && self.floor_used.iter().all(|u| !u.overlaps(obb))
    }

    /// Up to `tries` attempts at a free-standing floor object of half size `half`: a plan
    /// rectangle picked uniformly, a centre uniform in it shrunk by `margin`, then the yaw
    /// `turn` draws. The first footprint [`Self::floor_free`] accepts is reserved, grown by
    /// `grow`; returns the frame at the object's centre.
    pub(super) fn free_floor(
        &mut self,
        tries: usize,
        margin: f64,
        half: [f64; 2],
        grow: f64,
        turn: impl Fn(&mut Rng) -> f64,
    ) -> Option<Frame> {
        for _ in 0..tries {
            let q = *self.rng.pick(&self.rects);
            let c = [
                self.rng.uniform(q.x0 + margin, q.x1 - margin),
                self.rng.uniform(q.z0 + margin, q.z1 - margin),
            ];
            let yaw = turn(&mut self.rng);
            let obb = Obb { c, h: half, yaw };
            if c[0].is_finite() && c[1].is_finite() && self.floor_free(&obb) {
                self.floor_used.push(obb.grown(grow));
                return Some(Frame {
                    x: c[0],
                    z: c[1],
                    yaw,
                });
            }
        }
        None
    }

    /// A random wall, weighted by length, and a stretch `[s0, s1]` of length `width` on it
    /// (with `margin` to its ends), or `None` if the wall is too short.
    pub(super) fn wall_spot(&mut self, width: f64, margin: f64) -> Option<(usize, f64)> {
        let total: f64 = self.walls.iter().map(WallSeg::len).sum();
        let mut pick = self.rng.uniform(0.0, total);
        let mut wi = 0;
        for (i, w) in self.walls.iter().enumerate() {
            if pick < w.len() {
                wi = i;
                break;
            }
            pick -= w.len();
        }
        let len = self.walls[wi].len();
        if len < width + 2.0 * margin {
            return None;
        }
        Some((wi, self.rng.uniform(margin, len - width - margin)))
    }

    /// Up to `tries` attempts at a floor object of half size `(hx, hz)` with its back against
    /// a wall (local +z into the room), occupying elevations `e` on the wall. Returns the frame
    /// at the object's centre.
    pub(super) fn against_wall(
        &mut self,
        hx: f64,
        hz: f64,
        e: [f64; 2],
        tries: usize,
    ) -> Option<Frame> {
        for _ in 0..tries {
            let Some((wi, s0)) = self.wall_spot(2.0 * hx, 0.05) else {
                continue;
            };
            let w = self.walls[wi];
            let [x, z] = w.point(s0 + hx, hz + 0.01);
            let obb = Obb {
                c: [x, z],
                h: [hx, hz],
                yaw: w.yaw(),
            };
            if !self.wall_free(wi, [s0, s0 + 2.0 * hx], e) || !self.floor_free(&obb) {
                continue;
            }
            self.wall_used.push((wi, s0, s0 + 2.0 * hx, e[0], e[1]));
            self.floor_used.push(obb.grown(0.05));
            return Some(Frame { x, z, yaw: w.yaw() });
        }
        None
    }

    /// A flat object on a wall (door, window, board, picture): width, elevations, depth into
    /// the room. Returns the frame at the wall surface below the object's centre.
    pub(super) fn on_wall(
        &mut self,
        width: f64,
        e: [f64; 2],
        tries: usize,
    ) -> Option<(Frame, usize, f64)> {
        for _ in 0..tries {
            let Some((wi, s0)) = self.wall_spot(width, 0.15) else {
                continue;
            };
            if !self.wall_free(wi, [s0 - 0.05, s0 + width + 0.05], e) {
                continue;
            }
            let w = self.walls[wi];
            // The wall stretch must face the room along its whole width: probe just inside.
            let ok = (0..=4).all(|k| {
                let [x, z] = w.point(s0 + width * k as f64 / 4.0, 0.05);
                self.inside(x, z)
            });
            if !ok {
                continue;
            }
            self.wall_used.push((wi, s0, s0 + width, e[0], e[1]));
            let [x, z] = w.point(s0 + width / 2.0, 0.0);
            return Some((Frame { x, z, yaw: w.yaw() }, wi, s0));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    #[test]
    fn obb_overlap_and_distance() {
        let a = Obb {
            c: [0.0, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        let b = Obb {
            c: [2.2, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        assert!(!a.overlaps(&b));
        assert!(a.overlaps(&b.grown(0.3)));
        let turned = Obb {
            c: [1.9, 0.0],
            h: [1.0, 0.1],
            yaw: FRAC_PI_2,
        };
        assert!(!a.overlaps(&turned));
        assert!((b.distance_to_origin() - 1.2).abs() < 1e-12);
        assert_eq!(a.distance_to_origin(), 0.0);
    }
}
