//! Furniture on the floor (step 3 of the [module docs](super)): bookcases and sofas against
//! walls, tables with chairs around them, single chairs.

use std::f64::consts::{FRAC_PI_2, PI};

use super::class::*;
use super::placement::Frame;
use super::{Builder, Rect};
use crate::data::panorama::appearance::{pick_srgb, srgb, tint, vary, Pattern, Rgb};
use crate::data::rng::Rng;

impl Builder {
    pub(super) fn bookcases(&mut self) {
        let n = self.rng.int(0, 3);
        let wood = pick_srgb(
            &mut self.rng,
            &[0x966941, 0xC8AA7D, 0xA0A2A8, 0x5A3C28, 0xE1E1DC],
        );
        for _ in 0..n {
            let hx = self.rng.uniform(0.4, 1.0);
            let hz = self.rng.uniform(0.15, 0.22);
            let top = self.rng.uniform(1.0, 2.2).min(self.height - 0.2);
            let Some(f) = self.against_wall(hx, hz, [0.0, top], 20) else {
                continue;
            };
            let frame_colour = vary(wood, &mut self.rng, 0.05);
            let frame_mat = self.material(
                frame_colour,
                tint(frame_colour, 0.8),
                Pattern::Planks {
                    width: 0.3,
                    length: 2.5,
                },
            );
            let back = self.plain(tint(frame_colour, 0.55), 0.05);
            let t = 0.025;
            self.begin();
            // Back panel (against the wall, local -z), sides, top, plinth.
            let (side, panel) = ([t / 2.0, hz], [hx - t, hz]);
            self.cuboids(
                &f,
                BOOKCASE,
                &[
                    ([0.0, -hz + 0.01], [0.0, top], [hx, 0.01], back),
                    ([-hx + t / 2.0, 0.0], [0.0, top], side, frame_mat),
                    ([hx - t / 2.0, 0.0], [0.0, top], side, frame_mat),
                    ([0.0, 0.0], [top - t, top], [hx, hz], frame_mat),
                    ([0.0, 0.0], [0.0, 0.08], panel, frame_mat),
                ],
            );
            let shelves = ((top - 0.1) / self.rng.uniform(0.3, 0.4)).floor().max(1.0) as usize;
            let pitch = (top - t - 0.08) / shelves as f64;
            for k in 0..shelves {
                let e0 = 0.08 + k as f64 * pitch;
                if k > 0 {
                    let shelf = [e0 - t / 2.0, e0 + t / 2.0];
                    self.cuboid(&f, [0.0, 0.0], shelf, panel, BOOKCASE, frame_mat);
                }
                if self.rng.chance(0.85) {
                    // Books: a slab recessed 2-8 cm from the front, as tall as the compartment.
                    let recess = self.rng.uniform(0.02, 0.08);
                    let (b0, b1) = (e0 + t / 2.0, e0 + pitch - t / 2.0);
                    let half_height = ((b1 - b0) / 2.0) as f32;
                    let books = self.material(
                        [0.5; 3],
                        tint(frame_colour, 0.4),
                        Pattern::Books { half_height },
                    );
                    let depth = hz - recess / 2.0 - 0.01;
                    self.cuboid(
                        &f,
                        [0.0, -recess / 2.0 + 0.0],
                        [b0, b1],
                        [hx - t, depth - 0.01],
                        BOOKCASE,
                        books,
                    );
                }
            }
            self.end();
        }
    }

    /// Four square legs 5 cm wide at `(+-corner[0], +-corner[1])` in `f`, from the floor to
    /// elevation `top`.
    fn legs(&mut self, f: &Frame, corner: [f64; 2], top: f64, class: u8, mat: u16) {
        for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            let at = [sx * corner[0], sz * corner[1]];
            self.cuboid(f, at, [0.0, top], [0.025, 0.025], class, mat);
        }
    }

    pub(super) fn fabric(&mut self) -> Rgb {
        let c = pick_srgb(
            &mut self.rng,
            &[
                0x5F4632, 0x78787D, 0x32416E, 0x8C2D28, 0x3C5F46, 0x232326, 0xBEAF96,
            ],
        );
        vary(c, &mut self.rng, 0.08)
    }

    pub(super) fn sofas(&mut self) {
        let n = if self.rng.chance(0.5) {
            self.rng.int(1, 2)
        } else {
            0
        };
        for _ in 0..n {
            let hx = self.rng.uniform(0.75, 1.15);
            let hz = self.rng.uniform(0.4, 0.48);
            let seat = self.rng.uniform(0.4, 0.46);
            let back_top = self.rng.uniform(0.75, 0.9);
            let Some(f) = self.against_wall(hx, hz, [0.0, back_top], 20) else {
                continue;
            };
            let c = self.fabric();
            let weave = Pattern::Fabric {
                freq: 70.0,
                amp: 0.12,
            };
            let mat = self.material(c, c, weave);
            let cushion = self.material(tint(c, 1.1), c, weave);
            let feet = self.plain(srgb(40, 35, 30), 0.05);
            let arm = 0.12;
            self.begin();
            // Base, back, two arms.
            let (arm_e, arm_half) = ([seat - 0.1, seat + 0.15], [arm / 2.0, hz - 0.05]);
            self.cuboids(
                &f,
                SOFA,
                &[
                    ([0.0, 0.0], [0.06, seat - 0.1], [hx, hz], mat),
                    ([0.0, -hz + 0.1], [seat - 0.1, back_top], [hx, 0.1], mat),
                    ([-hx + arm / 2.0, 0.05], arm_e, arm_half, mat),
                    ([hx - arm / 2.0, 0.05], arm_e, arm_half, mat),
                ],
            );
            let cushions = if hx > 0.95 { 3 } else { 2 };
            let inner = hx - arm;
            let cw = 2.0 * inner / cushions as f64;
            for k in 0..cushions {
                let x = -inner + cw * (k as f64 + 0.5);
                self.cuboid(
                    &f,
                    [x, 0.08],
                    [seat - 0.1, seat],
                    [cw / 2.0 - 0.01, hz - 0.16],
                    SOFA,
                    cushion,
                );
            }
            self.legs(&f, [hx - 0.06, hz - 0.06], 0.06, SOFA, feet);
            self.end();
        }
    }

    /// One chair at `f` facing local +z (seat centre at the frame origin).
    pub(super) fn chair(&mut self, f: &Frame, seat_mat: u16, leg_mat: u16, office: bool) {
        let hs = 0.23;
        let seat = 0.46;
        self.begin();
        // Seat and back rest.
        let back_e = [seat + 0.08, seat + 0.5];
        self.cuboids(
            f,
            CHAIR,
            &[
                ([0.0, 0.0], [seat - 0.05, seat], [hs, hs], seat_mat),
                ([0.0, -hs + 0.02], back_e, [hs - 0.01, 0.02], seat_mat),
            ],
        );
        if office {
            self.cylinder(f, [0.0, 0.0], 0.025, [0.08, seat - 0.05], CHAIR, leg_mat);
            self.cylinder(f, [0.0, 0.0], 0.3, [0.03, 0.08], CHAIR, leg_mat);
            // Arm rests.
            for sx in [-1.0, 1.0] {
                let at = [sx * (hs + 0.02), 0.0];
                self.cuboids(
                    f,
                    CHAIR,
                    &[
                        (at, [seat + 0.16, seat + 0.19], [0.025, 0.14], leg_mat),
                        (at, [seat, seat + 0.16], [0.01, 0.015], leg_mat),
                    ],
                );
            }
        } else {
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let top = if sz < 0.0 { seat + 0.1 } else { seat - 0.05 };
                self.cuboid(
                    f,
                    [sx * (hs - 0.02), sz * (hs - 0.02)],
                    [0.0, top],
                    [0.015, 0.015],
                    CHAIR,
                    leg_mat,
                );
            }
        }
        self.end();
    }

    pub(super) fn chair_style(&mut self) -> (u16, u16, bool) {
        let c = self.fabric();
        let seat = self.material(
            c,
            c,
            Pattern::Fabric {
                freq: 80.0,
                amp: 0.1,
            },
        );
        let leg_c = pick_srgb(&mut self.rng, &[0x28282A, 0xAAACB2, 0x785537]);
        let legs = self.plain(leg_c, 0.03);
        (seat, legs, self.rng.chance(0.5))
    }

    pub(super) fn tables(&mut self) {
        let area: f64 = self.rects.iter().map(Rect::area).sum();
        let n = self.rng.int(0, ((area / 10.0) as usize + 1).min(5));
        let (chair_seat, chair_legs, office) = self.chair_style();
        let r = &mut self.rng;
        let top_c = pick_srgb(r, &[0xA07346, 0xD2B991, 0xEBEBE6, 0x787A80, 0x463223]);
        for _ in 0..n {
            let hx = self.rng.uniform(0.4, 1.2);
            let hz = self.rng.uniform(0.3, 0.5);
            let height = self.rng.uniform(0.72, 0.77);
            let yaw = if self.rng.chance(0.75) {
                self.rng.below(4) as f64 * FRAC_PI_2
            } else {
                self.rng.uniform(0.0, PI)
            };
            let chairs_long = self.rng.int(0, (hx / 0.35) as usize).min(3);
            let chairs_end = self.rng.int(0, 1);
            // The footprint includes room for the chairs.
            let (gx, gz) = (
                hx + if chairs_end > 0 { 0.6 } else { 0.05 },
                hz + if chairs_long > 0 { 0.6 } else { 0.05 },
            );
            let Some(f) = self.free_floor(25, 0.0, [gx, gz], 0.05, |_| yaw) else {
                continue;
            };
            let top_colour = vary(top_c, &mut self.rng, 0.05);
            let top_mat = if self.rng.chance(0.5) {
                self.material(
                    top_colour,
                    tint(top_colour, 0.8),
                    Pattern::Planks {
                        width: 0.25,
                        length: 3.0,
                    },
                )
            } else {
                self.plain(top_colour, 0.04)
            };
            let leg_c =
                *self
                    .rng
                    .pick(&[srgb(45, 45, 48), srgb(175, 178, 182), tint(top_colour, 0.8)]);
            let leg_mat = self.plain(leg_c, 0.03);
            let t = self.rng.uniform(0.025, 0.05);
            self.begin();
            let top = [height - t, height];
            self.cuboid(&f, [0.0, 0.0], top, [hx, hz], TABLE, top_mat);
            if self.rng.chance(0.8) {
                self.legs(&f, [hx - 0.06, hz - 0.06], height - t, TABLE, leg_mat);
            } else {
                // Panel ends (desk style).
                for sx in [-1.0, 1.0] {
                    let (at, half) = ([sx * (hx - 0.03), 0.0], [0.015, hz - 0.04]);
                    self.cuboid(&f, at, [0.0, height - t], half, TABLE, leg_mat);
                }
            }
            self.end();
            self.table_clutter(&f, hx, hz, height);
            let style = (chair_seat, chair_legs, office);
            self.table_chairs(&f, [hx, hz], [chairs_long, chairs_end], style);
        }
    }

    /// Chairs around the table at `f` of half sizes `[hx, hz]`: `chairs_long` on each long side,
    /// `chairs_end` (0 or 1) at one end, facing the table, pulled out 0.15-0.45 m, turned +-20
    /// degrees; about one place in seven stays empty. The style is [`Builder::chair_style`]'s.
    fn table_chairs(
        &mut self,
        f: &Frame,
        [hx, hz]: [f64; 2],
        [chairs_long, chairs_end]: [usize; 2],
        (seat, legs, office): (u16, u16, bool),
    ) {
        let mut spots = Vec::new();
        for side in [-1.0, 1.0] {
            for k in 0..chairs_long {
                let x = -hx + 2.0 * hx * (k as f64 + 0.5) / chairs_long as f64;
                spots.push((
                    x,
                    side * (hz + self.rng.uniform(0.05, 0.35)),
                    if side > 0.0 { PI } else { 0.0 },
                ));
            }
        }
        if chairs_end > 0 {
            let side = if self.rng.chance(0.5) { -1.0 } else { 1.0 };
            spots.push((
                side * (hx + self.rng.uniform(0.05, 0.35)),
                0.0,
                -side * FRAC_PI_2,
            ));
        }
        for (x, z, facing) in spots {
            if self.rng.chance(0.15) {
                continue; // an empty place
            }
            let jitter = self.rng.uniform(-0.35, 0.35);
            let cf = f.sub(x, z, facing + jitter);
            self.chair(&cf, seat, legs, office);
        }
    }

    pub(super) fn single_chairs(&mut self) {
        let n = self.rng.int(0, 3);
        let (seat, legs, office) = self.chair_style();
        for _ in 0..n {
            let turn = |r: &mut Rng| r.uniform(0.0, 2.0 * PI);
            if let Some(f) = self.free_floor(15, 0.0, [0.3, 0.3], 0.05, turn) {
                self.chair(&f, seat, legs, office);
            }
        }
    }
}
