//! What sits flat on the walls (step 2 of the [module docs](super)): doors, windows and boards,
//! each on a free stretch of wall that faces the room.

use super::class::*;
use super::placement::Obb;
use super::Builder;
use crate::data::panorama::appearance::{pick_srgb, srgb, tint, vary, Pattern};

impl Builder {
    pub(super) fn doors(&mut self) {
        let n = self.rng.int(1, 3);
        for _ in 0..n {
            let double = self.rng.chance(0.2);
            let width = if double {
                self.rng.uniform(1.5, 1.9)
            } else {
                self.rng.uniform(0.82, 1.0)
            };
            let top = self.rng.uniform(2.0, 2.3).min(self.height - 0.15);
            let frame_w = 0.06;
            let Some((f, wi, s0)) = self.on_wall(width + 2.0 * frame_w, [0.0, top + frame_w], 20)
            else {
                continue;
            };
            // Keep the doorway clear of furniture: 0.9 m in front of it.
            let w = self.walls[wi];
            let [x, z] = w.point(s0 + width / 2.0 + frame_w, 0.45);
            self.floor_used.push(Obb {
                c: [x, z],
                h: [width / 2.0 + frame_w, 0.45],
                yaw: w.yaw(),
            });
            let r = &mut self.rng;
            let leaf = pick_srgb(
                r,
                &[0x8C5C34, 0xBE9664, 0x969BA2, 0x3E527A, 0xDEDCD6, 0x8C2A24],
            );
            let leaf = vary(leaf, r, 0.06);
            let leaf_mat = self.material(
                leaf,
                tint(leaf, 0.8),
                Pattern::Planks {
                    width: width as f32,
                    length: 2.4,
                },
            );
            let frame_colour = if self.rng.chance(0.5) {
                tint(leaf, 0.75)
            } else {
                vary(srgb(200, 200, 198), &mut self.rng, 0.05)
            };
            let frame_mat = self.plain(frame_colour, 0.05);
            let handle_mat = self.plain(srgb(180, 180, 185), 0.02);
            self.begin();
            let (hw, fw) = (width / 2.0, frame_w);
            // Leaf: 4 cm thick, 2 cm proud of the wall; frame (two jambs, a head): 3 cm proud.
            let (jamb_e, jamb) = ([0.0, top + fw], [fw / 2.0, 0.03]);
            self.cuboids(
                &f,
                DOOR,
                &[
                    ([0.0, 0.0], [0.0, top], [hw, 0.02], leaf_mat),
                    ([-hw - fw / 2.0, 0.0], jamb_e, jamb, frame_mat),
                    ([hw + fw / 2.0, 0.0], jamb_e, jamb, frame_mat),
                    ([0.0, 0.0], [top, top + fw], [hw + fw, 0.03], frame_mat),
                ],
            );
            let handles: &[f64] = if double { &[-0.08, 0.08] } else { &[hw - 0.1] };
            for &hx in handles {
                self.cuboid(&f, [hx, 0.04], [1.0, 1.04], [0.06, 0.02], DOOR, handle_mat);
            }
            self.end();
        }
    }

    pub(super) fn windows(&mut self) {
        let corridor = self.rects.len() == 1
            && (self.rects[0].x1 - self.rects[0].x0).min(self.rects[0].z1 - self.rects[0].z0) < 2.7;
        let n = if corridor {
            self.rng.int(0, 1)
        } else {
            self.rng.int(0, 4)
        };
        let frame_colour = pick_srgb(&mut self.rng, &[0xE8E8E6, 0xA0A5AC, 0x28282A, 0x785232]);
        for _ in 0..n {
            let width = self.rng.uniform(0.8, 2.6);
            let sill = self.rng.uniform(0.7, 1.1);
            let top = (sill + self.rng.uniform(1.0, 1.8)).min(self.height - 0.2);
            if top - sill < 0.6 {
                continue;
            }
            let Some((f, _, _)) = self.on_wall(width, [sill, top], 20) else {
                continue;
            };
            let panes = [
                ((width / 0.7).round() as u8).clamp(1, 4),
                self.rng.int(1, 2) as u8,
            ];
            let mat = self.material(
                [1.0; 3],
                frame_colour,
                Pattern::Window {
                    half: [(width / 2.0) as f32, ((top - sill) / 2.0) as f32],
                    panes,
                },
            );
            let sill_mat = self.plain(tint(self.wall_colour, 0.95), 0.05);
            self.begin();
            let hw = width / 2.0;
            self.cuboid(&f, [0.0, 0.0], [sill, top], [hw, 0.02], WINDOW, mat);
            // The sill belongs to the wall.
            let ledge = [hw + 0.05, 0.06];
            self.cuboid(&f, [0.0, 0.06], [sill - 0.04, sill], ledge, WALL, sill_mat);
            self.end();
        }
    }

    pub(super) fn boards(&mut self) {
        let n = self.rng.int(0, 2);
        for _ in 0..n {
            let width = self.rng.uniform(1.0, 3.0);
            let bottom = self.rng.uniform(0.8, 1.05);
            let top = (bottom + self.rng.uniform(0.8, 1.3)).min(self.height - 0.3);
            let Some((f, _, _)) = self.on_wall(width, [bottom, top], 20) else {
                continue;
            };
            let r = &mut self.rng;
            let kind = r.below(3);
            let (base, ink, pattern) = match kind {
                0 => (
                    vary(srgb(242, 242, 240), r, 0.02),
                    pick_srgb(r, &[0x1E3CA0, 0xAA1E1E, 0x191919]),
                    Pattern::Board,
                ),
                1 => (
                    vary(srgb(38, 58, 48), r, 0.06),
                    srgb(215, 215, 205),
                    Pattern::Board,
                ),
                _ => (
                    vary(srgb(182, 142, 92), r, 0.06),
                    srgb(182, 142, 92),
                    Pattern::Fabric {
                        freq: 60.0,
                        amp: 0.2,
                    },
                ),
            };
            let mat = self.material(base, ink, pattern);
            let rim = self.plain(srgb(175, 178, 182), 0.03);
            self.begin();
            let (hw, t) = (width / 2.0, 0.025);
            // The surface, then its rim: bottom and top bars, left and right posts.
            let (bar, post) = ([hw + t, 0.02], [t / 2.0, 0.02]);
            self.cuboids(
                &f,
                BOARD,
                &[
                    ([0.0, 0.0], [bottom, top], [hw, 0.015], mat),
                    ([0.0, 0.0], [bottom - t, bottom], bar, rim),
                    ([0.0, 0.0], [top, top + t], bar, rim),
                    ([-hw - t / 2.0, 0.0], [bottom, top], post, rim),
                    ([hw + t / 2.0, 0.0], [bottom, top], post, rim),
                ],
            );
            // A marker tray on whiteboards.
            if kind == 0 {
                let tray_e = [bottom - 0.05, bottom - 0.03];
                self.cuboid(&f, [0.0, 0.04], tray_e, [hw * 0.6, 0.04], BOARD, rim);
            }
            self.end();
        }
    }
}
