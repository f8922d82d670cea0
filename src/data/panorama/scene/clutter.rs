//! Clutter (step 3 of the [module docs](super)): monitors, laptops, papers and mugs on tables;
//! cabinets, boxes, bins, plants and appliances on the floor; pictures, radiators and air
//! conditioners on the walls.

use std::f64::consts::PI;

use super::class::*;
use super::placement::Frame;
use super::Builder;
use crate::data::panorama::appearance::{pick_srgb, srgb, tint, vary, Pattern};
use crate::data::rng::Rng;

impl Builder {
    /// Monitors, laptops, papers, mugs, books on a table top.
    pub(super) fn table_clutter(&mut self, f: &Frame, hx: f64, hz: f64, height: f64) {
        let n = self.rng.int(0, 4);
        for _ in 0..n {
            let x = self.rng.uniform(-hx + 0.2, hx - 0.2);
            let z = self.rng.uniform(-hz + 0.15, hz - 0.15);
            let kind = self.rng.below(5);
            let item = f.sub(x, z, self.rng.uniform(-0.4, 0.4));
            self.begin();
            match kind {
                0 => {
                    let screen = self.material([0.03; 3], [0.03; 3], Pattern::Screen);
                    let body = self.plain(srgb(30, 30, 32), 0.03);
                    let w = self.rng.uniform(0.25, 0.35);
                    // Foot, neck, screen.
                    let (h, screen_e) = (height, [height + 0.1, height + 0.1 + w * 1.2]);
                    self.cuboids(
                        &item,
                        CLUTTER,
                        &[
                            ([0.0, 0.0], [h, h + 0.015], [0.1, 0.08], body),
                            ([0.0, -0.02], [h, h + 0.12], [0.025, 0.015], body),
                            ([0.0, 0.0], screen_e, [w, 0.02], screen),
                        ],
                    );
                }
                1 => {
                    let c = pick_srgb(&mut self.rng, &[0x28282C, 0xBEC0C4]);
                    let m = self.plain(c, 0.03);
                    // Base and lid.
                    let h = height;
                    self.cuboids(
                        &item,
                        CLUTTER,
                        &[
                            ([0.0, 0.0], [h, h + 0.02], [0.17, 0.12], m),
                            ([0.0, -0.12], [h + 0.02, h + 0.24], [0.17, 0.006], m),
                        ],
                    );
                }
                2 => {
                    let m = self.plain(srgb(240, 240, 235), 0.02);
                    let e = [height, height + 0.01];
                    self.cuboid(&item, [0.0, 0.0], e, [0.105, 0.15], CLUTTER, m);
                }
                3 => {
                    let c = vary(srgb(200, 60, 50), &mut self.rng, 0.3);
                    let m = self.plain(c, 0.05);
                    self.cylinder(&item, [0.0, 0.0], 0.04, [height, height + 0.1], CLUTTER, m);
                }
                _ => {
                    let c = vary(srgb(60, 90, 150), &mut self.rng, 0.3);
                    let m = self.plain(c, 0.05);
                    let h = self.rng.uniform(0.03, 0.12);
                    let e = [height, height + h];
                    self.cuboid(&item, [0.0, 0.0], e, [0.12, 0.09], CLUTTER, m);
                }
            }
            self.end();
        }
    }

    /// 2 to 10 pieces on the floor: cabinets against walls (one in five), free-standing boxes,
    /// bins, plants and appliances.
    pub(super) fn floor_clutter(&mut self) {
        let n = self.rng.int(2, 10);
        for _ in 0..n {
            match self.rng.below(5) {
                0 => self.cabinet(),
                kind => self.free_standing(kind),
            }
        }
    }

    /// A cabinet with drawer handles against a wall.
    fn cabinet(&mut self) {
        let hx = self.rng.uniform(0.2, 0.5);
        let hz = self.rng.uniform(0.2, 0.3);
        let top = self.rng.uniform(0.7, 1.3);
        let Some(f) = self.against_wall(hx, hz, [0.0, top], 10) else {
            return;
        };
        let c = vary(
            pick_srgb(&mut self.rng, &[0xB4B6BA, 0xD2C8AF, 0x5A5C62]),
            &mut self.rng,
            0.06,
        );
        let m = self.plain(c, 0.04);
        let handle = self.plain(tint(c, 0.5), 0.02);
        self.begin();
        self.cuboid(&f, [0.0, 0.0], [0.0, top], [hx, hz], CLUTTER, m);
        let drawers = self.rng.int(1, 4);
        for k in 0..drawers {
            let e = top * (k as f64 + 0.5) / drawers as f64;
            let (at, half) = ([0.0, hz + 0.01], [hx * 0.3, 0.01]);
            self.cuboid(&f, at, [e - 0.01, e + 0.01], half, CLUTTER, handle);
        }
        self.end();
    }

    /// A free-standing piece of kind 1 (boxes), 2 (a bin), 3 (a plant) or 4 (an appliance).
    fn free_standing(&mut self, kind: u64) {
        let r = self.rng.uniform(0.15, 0.35);
        let turn = |r: &mut Rng| r.uniform(0.0, PI);
        let Some(f) = self.free_floor(15, 0.0, [r, r], 0.05, turn) else {
            return;
        };
        self.begin();
        match kind {
            1 => {
                let c = vary(srgb(170, 130, 85), &mut self.rng, 0.1);
                let m = self.plain(c, 0.1);
                let h = self.rng.uniform(0.2, 0.6);
                self.cuboid(&f, [0.0, 0.0], [0.0, h], [r, r * 0.8], CLUTTER, m);
                if self.rng.chance(0.4) {
                    let h2 = h + self.rng.uniform(0.15, 0.4);
                    let g = f.sub(0.0, 0.0, self.rng.uniform(-0.3, 0.3));
                    let half = [r * 0.7, r * 0.6];
                    self.cuboid(&g, [0.0, 0.0], [h, h2], half, CLUTTER, m);
                }
            }
            2 => {
                let c = pick_srgb(&mut self.rng, &[0x3C5AA0, 0x505055, 0x28783C]);
                let m = self.plain(c, 0.05);
                let h = self.rng.uniform(0.3, 0.6);
                self.cylinder(&f, [0.0, 0.0], r * 0.7, [0.0, h], CLUTTER, m);
            }
            3 => {
                let c = vary(srgb(150, 80, 50), &mut self.rng, 0.1);
                let pot = self.plain(c, 0.05);
                let c = vary(srgb(55, 110, 45), &mut self.rng, 0.1);
                let leaves = self.material(
                    c,
                    srgb(30, 70, 25),
                    Pattern::Fabric {
                        freq: 25.0,
                        amp: 0.35,
                    },
                );
                let h = self.rng.uniform(0.25, 0.4);
                self.cylinder(&f, [0.0, 0.0], r * 0.6, [0.0, h], CLUTTER, pot);
                let top = h + self.rng.uniform(0.4, 1.0);
                self.cylinder(&f, [0.0, 0.0], r, [h, top], CLUTTER, leaves);
            }
            _ => {
                // A printer / appliance.
                let m = self.plain(srgb(215, 215, 210), 0.03);
                let d = self.plain(srgb(50, 50, 52), 0.03);
                self.cuboid(&f, [0.0, 0.0], [0.0, 0.7], [r, r], CLUTTER, d);
                self.cuboid(&f, [0.0, 0.0], [0.7, 1.0], [r, r], CLUTTER, m);
            }
        }
        self.end();
    }

    /// Pictures, posters, radiators and air conditioners on the walls.
    pub(super) fn wall_clutter(&mut self) {
        let n = self.rng.int(0, 6);
        for _ in 0..n {
            let kind = self.rng.below(3);
            let (width, e) = match kind {
                0 => {
                    let w = self.rng.uniform(0.3, 1.2);
                    let b = self.rng.uniform(1.2, 1.6);
                    (
                        w,
                        [
                            b,
                            (b + w * self.rng.uniform(0.6, 1.4)).min(self.height - 0.2),
                        ],
                    )
                }
                1 => (
                    self.rng.uniform(0.6, 1.4),
                    [0.15, self.rng.uniform(0.5, 0.7)],
                ),
                _ => (0.9, [self.height - 0.6, self.height - 0.3]),
            };
            let Some((f, _, _)) = self.on_wall(width, e, 10) else {
                continue;
            };
            self.begin();
            match kind {
                0 => {
                    let c = vary(
                        pick_srgb(&mut self.rng, &[0xB43C32, 0x3C78AA, 0xDCC878, 0x5A8C50]),
                        &mut self.rng,
                        0.2,
                    );
                    let m = self.material(
                        c,
                        tint(c, 0.4),
                        Pattern::Plain {
                            freq: 6.0,
                            amp: 0.5,
                        },
                    );
                    let frame = self.plain(srgb(30, 30, 30), 0.02);
                    // The picture, then the bottom and top of its frame.
                    let (hw, bar) = (width / 2.0, [width / 2.0 + 0.02, 0.02]);
                    self.cuboids(
                        &f,
                        CLUTTER,
                        &[
                            ([0.0, 0.0], e, [hw, 0.015], m),
                            ([0.0, 0.0], [e[0] - 0.02, e[0]], bar, frame),
                            ([0.0, 0.0], [e[1], e[1] + 0.02], bar, frame),
                        ],
                    );
                }
                1 => {
                    let m = self.material(
                        srgb(230, 230, 225),
                        srgb(150, 150, 150),
                        Pattern::Tiles {
                            size: 0.06,
                            grout: 0.015,
                            jitter: 0.02,
                        },
                    );
                    self.cuboid(&f, [0.0, 0.0], e, [width / 2.0, 0.05], CLUTTER, m);
                }
                _ => {
                    let m = self.plain(srgb(235, 235, 232), 0.03);
                    self.cuboid(&f, [0.0, 0.0], e, [width / 2.0, 0.11], CLUTTER, m);
                }
            }
            self.end();
        }
    }
}
