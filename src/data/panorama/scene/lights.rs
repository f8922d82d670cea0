//! Ceiling light panels and their point lights (step 4 of the [module docs](super)).

use super::class::*;
use super::placement::{Frame, Obb};
use super::{Builder, Light, MAX_LIGHTS};
use crate::data::panorama::appearance::{mix, srgb, Pattern};

impl Builder {
    /// Ceiling light panels and their point lights, on a ~3 m grid per rectangle.
    pub(super) fn lights(&mut self) {
        let warm = self.rng.uniform(0.0, 1.0) as f32;
        let colour = mix(srgb(255, 255, 250), srgb(255, 235, 200), warm);
        let rim = srgb(200, 200, 200);
        let intensity = self.rng.uniform(0.9, 1.5) as f32;
        let long = self.rng.chance(0.4);
        let half = if long { [0.6, 0.15] } else { [0.3, 0.3] };
        let mat = self.material(
            colour,
            rim,
            Pattern::Light {
                half: [half[0] as f32, half[1] as f32],
            },
        );
        let mut spots = Vec::new();
        for q in self.rects.clone() {
            let nx = (((q.x1 - q.x0) / 3.0).round() as usize).clamp(1, 3);
            let nz = (((q.z1 - q.z0) / 3.0).round() as usize).clamp(1, 3);
            for i in 0..nx {
                for k in 0..nz {
                    let x = q.x0 + (q.x1 - q.x0) * (i as f64 + 0.5) / nx as f64;
                    let z = q.z0 + (q.z1 - q.z0) * (k as f64 + 0.5) / nz as f64;
                    spots.push([x, z]);
                }
            }
        }
        // Keep at most MAX_LIGHTS, spread out: a random subset.
        self.rng.shuffle(&mut spots);
        let mut placed = 0;
        for [x, z] in spots {
            if placed == MAX_LIGHTS {
                break;
            }
            let obb = Obb {
                c: [x, z],
                h: half,
                yaw: 0.0,
            };
            if self.beams.iter().any(|b| b.overlaps(&obb.grown(0.05))) {
                continue;
            }
            self.begin();
            let frame = Frame { x, z, yaw: 0.0 };
            let e = [self.height - 0.012, self.height];
            self.cuboid(&frame, [0.0, 0.0], e, half, CEILING, mat);
            self.prims.last_mut().expect("just pushed").shadow = false;
            self.end();
            self.lights.push(Light {
                pos: [x, self.y(self.height - 0.12), z],
                intensity,
            });
            placed += 1;
        }
    }
}
