//! The room itself (step 1 and 2 of the [module docs](super)): floor plan, camera position,
//! floor, ceiling and walls with their materials, ceiling beams and columns.

use super::class::*;
use super::placement::{Frame, Obb};
use super::{Builder, Group, Rect, WallSeg};
use crate::data::panorama::appearance::{pick_srgb, srgb, tint, vary, Pattern, Rgb};
use crate::data::panorama::geometry::{Aabb, Shape};

impl Builder {
    /// Floor plan, camera position, walls (step 1 of the module docs).
    pub(super) fn room(&mut self) {
        let r = &mut self.rng;
        let kind = r.f64();
        let (mut rects, height) = if kind < 0.5 {
            let (w, l) = (r.uniform(3.0, 9.0), r.uniform(3.0, 12.0));
            (vec![[0.0, w, 0.0, l]], r.uniform(2.6, 3.8))
        } else if kind < 0.8 {
            let (w, l) = (r.uniform(4.0, 9.0), r.uniform(3.0, 8.0));
            let (w2, l2) = (r.uniform(2.0, w - 1.5), r.uniform(2.0, 6.0));
            (
                vec![[0.0, w, 0.0, l], [0.0, w2, l, l + l2]],
                r.uniform(2.6, 3.6),
            )
        } else {
            let (w, l) = (r.uniform(1.8, 2.6), r.uniform(8.0, 20.0));
            (vec![[0.0, w, 0.0, l]], r.uniform(2.5, 3.2))
        };
        // Turn by multiples of 90 degrees and mirror: swap axes, negate x, negate z.
        let (swap, fx, fz) = (r.chance(0.5), r.chance(0.5), r.chance(0.5));
        for q in rects.iter_mut() {
            if swap {
                *q = [q[2], q[3], q[0], q[1]];
            }
            if fx {
                *q = [-q[1], -q[0], q[2], q[3]];
            }
            if fz {
                *q = [q[0], q[1], -q[3], -q[2]];
            }
        }
        let mut rects: Vec<Rect> = rects
            .iter()
            .map(|q| Rect {
                x0: q[0],
                x1: q[1],
                z0: q[2],
                z1: q[3],
            })
            .collect();
        // Camera: in a rectangle chosen by area, >= 0.6 m from its walls.
        let total: f64 = rects.iter().map(Rect::area).sum();
        let mut pick = r.uniform(0.0, total);
        let mut chosen = rects[0];
        for q in &rects {
            if pick < q.area() {
                chosen = *q;
                break;
            }
            pick -= q.area();
        }
        let m = 0.6;
        let cx = r.uniform(chosen.x0 + m, chosen.x1 - m);
        let cz = r.uniform(chosen.z0 + m, chosen.z1 - m);
        for q in rects.iter_mut() {
            q.x0 -= cx;
            q.x1 -= cx;
            q.z0 -= cz;
            q.z1 -= cz;
        }
        self.cam_h = r.uniform(1.2, 1.7);
        self.height = height;
        self.rects = rects;
        self.walls = walls_of(&self.rects);
    }

    /// Floor, ceiling, walls and their materials (group 0).
    pub(super) fn structure(&mut self) {
        self.begin();
        let floor = self.floor_material();
        let ceiling = self.ceiling_material();
        let wall = self.wall_material();
        let (floor_y, ceil_y) = (self.y(0.0), self.y(self.height));
        self.push(Shape::Plane { y: floor_y }, FLOOR, floor);
        self.push(Shape::Plane { y: ceil_y }, CEILING, ceiling);
        // Walls overlap by 0.1 mm at the ends so corners stay sealed against round-off.
        for w in self.walls.clone() {
            self.push(
                Shape::Wall {
                    axis: w.axis,
                    at: w.at,
                    lo: w.lo - 1e-4,
                    hi: w.hi + 1e-4,
                },
                WALL,
                wall,
            );
        }
        // Group 0 is tested without culling: give it infinite bounds.
        let (start, end) = (self.group_start, self.prims.len());
        self.groups.push(Group {
            bounds: Aabb {
                lo: [f64::NEG_INFINITY; 3],
                hi: [f64::INFINITY; 3],
            },
            start,
            end,
        });
    }

    /// The floor's material: tiles, planks, carpet or plain concrete.
    fn floor_material(&mut self) -> u16 {
        let r = &mut self.rng;
        let floor_kind = r.below(4);
        let (base, alt, pattern) = match floor_kind {
            0 => {
                let c = pick_srgb(r, &[0xC8BEAA, 0xA5A5A0, 0xDCDAD2, 0xAA694B]);
                let size = *r.pick(&[0.3f32, 0.4, 0.5, 0.6]);
                (
                    vary(c, r, 0.08),
                    tint(c, 0.6),
                    Pattern::Tiles {
                        size,
                        grout: 0.006,
                        jitter: 0.08,
                    },
                )
            }
            1 => {
                let c = pick_srgb(r, &[0x96643C, 0xB98C5A, 0x6E482D]);
                (
                    vary(c, r, 0.1),
                    tint(c, 0.7),
                    Pattern::Planks {
                        width: r.uniform(0.1, 0.2) as f32,
                        length: r.uniform(0.8, 1.8) as f32,
                    },
                )
            }
            2 => {
                let c = pick_srgb(r, &[0x5A5A64, 0x3C486E, 0x733E3E, 0x506450, 0x82786E]);
                (
                    vary(c, r, 0.1),
                    c,
                    Pattern::Fabric {
                        freq: 45.0,
                        amp: 0.15,
                    },
                )
            }
            _ => {
                let c = vary(srgb(150, 150, 145), r, 0.1);
                (
                    c,
                    c,
                    Pattern::Plain {
                        freq: 1.5,
                        amp: 0.2,
                    },
                )
            }
        };
        self.material(base, alt, pattern)
    }

    /// The ceiling's material (tiles or plain), remembering its colour for the beams.
    fn ceiling_material(&mut self) -> u16 {
        let r = &mut self.rng;
        let ceiling_colour = vary(srgb(232, 232, 226), r, 0.04);
        let ceiling_pattern = if r.chance(0.6) {
            Pattern::Tiles {
                size: 0.6,
                grout: 0.012,
                jitter: 0.03,
            }
        } else {
            Pattern::Plain {
                freq: 1.0,
                amp: 0.05,
            }
        };
        self.ceiling_colour = ceiling_colour;
        self.material(ceiling_colour, tint(ceiling_colour, 0.75), ceiling_pattern)
    }

    /// The walls' material (painted blocks or plain paint), remembering its colour for the sills
    /// and columns.
    fn wall_material(&mut self) -> u16 {
        let r = &mut self.rng;
        let wall_colour = vary(
            pick_srgb(
                r,
                &[
                    0xE6E4DC, 0xE1DAC6, 0xC8CDD4, 0xD4E1D4, 0xEBE0C4, 0xBEC8DA, 0xD7C8BE,
                ],
            ),
            r,
            0.05,
        );
        self.wall_colour = wall_colour;
        if r.chance(0.2) {
            // Painted concrete blocks: the wall colour with slightly darker mortar.
            self.material(wall_colour, tint(wall_colour, 0.8), Pattern::Blocks)
        } else {
            self.plain(wall_colour, 0.06)
        }
    }

    /// A plain material for a structural part: half the time `tint(like, t)` (the ceiling's or
    /// walls' colour), else a variation of `grey` by `amount`; blotches of amplitude `amp`.
    fn matching_plain(&mut self, like: Rgb, t: f32, grey: Rgb, amount: f32, amp: f32) -> u16 {
        let colour = if self.rng.chance(0.5) {
            tint(like, t)
        } else {
            vary(grey, &mut self.rng, amount)
        };
        self.plain(colour, amp)
    }

    /// Ceiling beams spanning one rectangle of the plan.
    pub(super) fn beams(&mut self) {
        if !self.rng.chance(0.35) {
            return;
        }
        let n = self.rng.int(1, 2);
        let mat = self.matching_plain(self.ceiling_colour, 0.92, srgb(175, 175, 170), 0.06, 0.12);
        for _ in 0..n {
            let q = *self.rng.pick(&self.rects.clone());
            let along_x = self.rng.chance(0.5);
            let depth = self.rng.uniform(0.25, 0.6);
            let half_w = self.rng.uniform(0.12, 0.25);
            let e = [self.height - depth, self.height];
            let (c, h) = if along_x {
                let z = self.rng.uniform(q.z0 + 0.5, q.z1 - 0.5);
                ([(q.x0 + q.x1) / 2.0, z], [(q.x1 - q.x0) / 2.0, half_w])
            } else {
                let x = self.rng.uniform(q.x0 + 0.5, q.x1 - 0.5);
                ([x, (q.z0 + q.z1) / 2.0], [half_w, (q.z1 - q.z0) / 2.0])
            };
            // A beam right above the camera would hide the ceiling test cases and the
            // lights; keep a little distance.
            let obb = Obb { c, h, yaw: 0.0 };
            if obb.distance_to_origin() < 0.3
                || self.beams.iter().any(|b| b.overlaps(&obb.grown(0.3)))
            {
                continue;
            }
            self.beams.push(obb);
            self.begin();
            let frame = Frame {
                x: c[0],
                z: c[1],
                yaw: 0.0,
            };
            self.cuboid(&frame, [0.0, 0.0], e, h, BEAM, mat);
            self.end();
        }
    }

    pub(super) fn columns(&mut self) {
        if !self.rng.chance(0.4) {
            return;
        }
        let n = self.rng.int(1, 3);
        let mat = self.matching_plain(self.wall_colour, 0.9, srgb(170, 170, 165), 0.08, 0.1);
        let e = [0.0, self.height];
        for _ in 0..n {
            let half = self.rng.uniform(0.15, 0.32);
            let frame = if self.rng.chance(0.7) {
                // Half sunk into a wall.
                self.against_wall(half, half / 2.0, e, 20)
                    .map(|f| f.sub(0.0, -half / 2.0, 0.0))
            } else {
                self.free_floor(20, 1.0, [half, half], 0.3, |_| 0.0)
            };
            if let Some(f) = frame {
                self.begin();
                self.cuboid(&f, [0.0, 0.0], e, [half, half], COLUMN, mat);
                self.end();
            }
        }
    }
}

/// The walls of a plan made of one rectangle, or of two sharing part of a side (an L): the
/// outline of the union, split into axis-aligned segments, each with its inward side.
pub(super) fn walls_of(rects: &[Rect]) -> Vec<WallSeg> {
    let inside = |x: f64, z: f64| rects.iter().any(|q| q.contains(x, z, -1e-9));
    let mut out = Vec::new();
    // Candidate breakpoints along each rectangle side: every rectangle's coordinates.
    let xs: Vec<f64> = rects.iter().flat_map(|q| [q.x0, q.x1]).collect();
    let zs: Vec<f64> = rects.iter().flat_map(|q| [q.z0, q.z1]).collect();
    let eps = 1e-3;
    for q in rects {
        // Sides x = const (axis 0) spanning z, and z = const (axis 2) spanning x.
        for (axis, at, lo, hi, cuts) in [
            (0, q.x0, q.z0, q.z1, &zs),
            (0, q.x1, q.z0, q.z1, &zs),
            (2, q.z0, q.x0, q.x1, &xs),
            (2, q.z1, q.x0, q.x1, &xs),
        ] {
            let mut pts: Vec<f64> = cuts.iter().copied().filter(|&c| c > lo && c < hi).collect();
            pts.push(lo);
            pts.push(hi);
            pts.sort_by(f64::total_cmp);
            pts.dedup();
            for seg in pts.windows(2) {
                let mid = (seg[0] + seg[1]) / 2.0;
                let probe = |off: f64| {
                    if axis == 0 {
                        inside(at + off, mid)
                    } else {
                        inside(mid, at + off)
                    }
                };
                let (plus, minus) = (probe(eps), probe(-eps));
                if plus == minus {
                    continue; // interior (shared) side
                }
                let w = WallSeg {
                    axis,
                    at,
                    lo: seg[0],
                    hi: seg[1],
                    inward: if plus { 1.0 } else { -1.0 },
                };
                if !out.contains(&w) {
                    out.push(w);
                }
            }
        }
    }
    // Merge collinear neighbours (a rectangle side cut where nothing happens).
    out.sort_by(|a, b| {
        (a.axis, a.at, a.inward, a.lo)
            .partial_cmp(&(b.axis, b.at, b.inward, b.lo))
            .expect("finite")
    });
    let mut merged: Vec<WallSeg> = Vec::new();
    for w in out {
        match merged.last_mut() {
            Some(m)
                if m.axis == w.axis
                    && m.at == w.at
                    && m.inward == w.inward
                    && (m.hi - w.lo).abs() < 1e-12 =>
            {
                m.hi = w.hi;
            }
            _ => merged.push(w),
        }
    }
    merged
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walls_of_an_l_shape() {
        let rects = [
            Rect {
                x0: 0.0,
                x1: 4.0,
                z0: 0.0,
                z1: 3.0,
            },
            Rect {
                x0: 0.0,
                x1: 2.0,
                z0: 3.0,
                z1: 5.0,
            },
        ];
        let walls = walls_of(&rects);
        // An L has six sides.
        assert_eq!(walls.len(), 6, "{walls:?}");
        let perimeter: f64 = walls.iter().map(WallSeg::len).sum();
        assert!((perimeter - (4.0 + 3.0 + 2.0 + 2.0 + 2.0 + 5.0)).abs() < 1e-12);
        // The reflex side z = 3 for x in [2, 4] faces -z (the room is below it).
        let reflex = walls.iter().find(|w| w.axis == 2 && w.at == 3.0).unwrap();
        assert_eq!((reflex.lo, reflex.hi, reflex.inward), (2.0, 4.0, -1.0));
    }
}
