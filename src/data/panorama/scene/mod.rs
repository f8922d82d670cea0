//! Procedural indoor scenes: a room with furniture, lights and per-class materials, built from
//! the primitives of [`super::geometry`] and traced analytically.
//!
//! Coordinates: metres, x right, y **down**, z forward, the panorama's camera centre at the
//! origin; "elevation" `e` is height above the floor, so `y = camera_height - e`.
//!
//! A scene is a pure function of its seed ([`Scene::generate`]):
//!
//! 1. **Room**: a box (50 %), an L-shape (30 %: two rectangles sharing a side) or a corridor
//!    (20 %), 1.8 to 20 m long, 2.5 to 3.8 m high; randomly turned by multiples of 90 degrees and
//!    mirrored. The camera stands 1.2 to 1.7 m above the floor, at least 0.6 m from the walls.
//! 2. **Structure**: floor, ceiling, walls; ceiling beams spanning a rectangle; columns against
//!    walls or free-standing; doors, windows and boards on walls (no two overlap on a wall).
//! 3. **Furniture** on the floor (never overlapping each other, the doorways, or a 0.6 m disc
//!    around the camera): tables with chairs around them, single chairs, sofas and bookcases
//!    against walls, clutter (cabinets, boxes, bins, plants; pictures and radiators on walls;
//!    monitors, laptops, papers, mugs on tables).
//! 4. **Lights**: ceiling light panels on a ~3 m grid (at most [`MAX_LIGHTS`]), each a point
//!    light 0.12 m below its panel, with shadow rays.
//!
//! Each piece of furniture is one [`Group`] with a bounding box, so a ray tests a handful of
//! boxes before it tests any part.

use std::f64::consts::{FRAC_PI_2, PI};

mod clutter;
mod furniture;
mod lights;
mod openings;
mod placement;
mod structure;

use super::appearance::{Material, Pattern, Rgb, FALLOFF_M};
use super::geometry::{dot, norm, scale, sub, Aabb, Hit, Ray, Shape, V3};
use crate::data::rng::{hash, Rng};
use placement::{Frame, Obb, WallSpan};

pub mod class {
    //! Class ids, each looked up by name in [`crate::data::CLASSES`] when compiling (a name
    //! that is not a class does not compile): one constant per class, named as the class.
    #![allow(missing_docs)]
    use crate::data::class_id;

    /// `pub const NAME: u8 = class_id("name");` for each class, and [`ALL`] listing them.
    macro_rules! class_ids {
        ($($id:ident = $name:literal),* $(,)?) => {
            $(pub const $id: u8 = class_id($name);)*
            /// Every class id with its name, in `CLASSES` order.
            pub const ALL: [(&str, u8); [$($name),*].len()] = [$(($name, $id)),*];
        };
    }

    class_ids! {
        BEAM = "beam", BOARD = "board", BOOKCASE = "bookcase", CEILING = "ceiling",
        CHAIR = "chair", CLUTTER = "clutter", COLUMN = "column", DOOR = "door", FLOOR = "floor",
        SOFA = "sofa", TABLE = "table", WALL = "wall", WINDOW = "window",
    }
}

/// Most ceiling lights in a scene (each costs one shadow ray per pixel).
pub const MAX_LIGHTS: usize = 4;

/// Clear radius around the camera in which no furniture stands, in metres (so the camera is
/// never inside an object and the straight-down ray meets the floor).
pub const CAMERA_CLEARANCE_M: f64 = 0.6;

/// One primitive: a shape, its class, its material and whether it casts shadows.
#[derive(Clone, Debug, PartialEq)]
pub struct Prim {
    /// Geometry.
    pub shape: Shape,
    /// Class id in [`crate::data::CLASSES`] order.
    pub class: u8,
    /// Index into [`Scene::materials`].
    pub material: u16,
    /// Whether it blocks shadow rays (light panels do not).
    pub shadow: bool,
}

/// A contiguous run of primitives (one piece of furniture) with its bounding box.
#[derive(Clone, Debug, PartialEq)]
pub struct Group {
    /// Bounds of every primitive of the group.
    pub bounds: Aabb,
    /// First primitive index.
    pub start: usize,
    /// One past the last primitive index.
    pub end: usize,
}

/// A point light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    /// Position, metres.
    pub pos: V3,
    /// Intensity `I` of the shading formula.
    pub intensity: f32,
}

/// An axis-aligned rectangle of the floor plan, in (x, z) metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    /// Smallest x.
    pub x0: f64,
    /// Largest x.
    pub x1: f64,
    /// Smallest z.
    pub z0: f64,
    /// Largest z.
    pub z1: f64,
}

impl Rect {
    fn contains(&self, x: f64, z: f64, margin: f64) -> bool {
        x >= self.x0 + margin
            && x <= self.x1 - margin
            && z >= self.z0 + margin
            && z <= self.z1 - margin
    }
    fn area(&self) -> f64 {
        (self.x1 - self.x0) * (self.z1 - self.z0)
    }
}

/// A wall of the floor plan: the vertical plane `coord[axis] = at` for the other horizontal
/// coordinate in `[lo, hi]`, with the room on the side `inward` (+1 or -1) of the plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallSeg {
    /// 0 (a plane x = at) or 2 (z = at).
    pub axis: usize,
    /// The plane's coordinate.
    pub at: f64,
    /// Lower end along the wall.
    pub lo: f64,
    /// Upper end along the wall.
    pub hi: f64,
    /// +1 or -1: the side of the plane the room is on.
    pub inward: f64,
}

impl WallSeg {
    fn len(&self) -> f64 {
        self.hi - self.lo
    }
    /// Floor point `(x, z)` at distance `s` along the wall, pushed `off` metres into the room.
    fn point(&self, s: f64, off: f64) -> [f64; 2] {
        match self.axis {
            0 => [self.at + self.inward * off, self.lo + s],
            _ => [self.lo + s, self.at + self.inward * off],
        }
    }
    /// The yaw that turns local +z into the room (local x then runs along the wall).
    fn yaw(&self) -> f64 {
        match self.axis {
            0 => self.inward * FRAC_PI_2,
            _ => {
                if self.inward > 0.0 {
                    0.0
                } else {
                    PI
                }
            }
        }
    }
}

/// A procedural room ready to be traced. Everything is public for tests and tools; build one
/// with [`Scene::generate`].
#[derive(Clone, Debug)]
pub struct Scene {
    /// Every primitive, grouped.
    pub prims: Vec<Prim>,
    /// Group 0 is the room structure (planes and walls) and is never culled.
    pub groups: Vec<Group>,
    /// The materials the primitives index.
    pub materials: Vec<Material>,
    /// Ceiling lights.
    pub lights: Vec<Light>,
    /// Camera height above the floor, metres (the floor is the plane `y = camera_height`).
    pub camera_height: f64,
    /// Floor-to-ceiling height, metres.
    pub room_height: f64,
    /// The floor plan (union of rectangles), camera at `(0, 0)`.
    pub footprint: Vec<Rect>,
    /// The walls of the plan.
    pub walls: Vec<WallSeg>,
    /// Ambient light level `A`.
    pub ambient: f32,
    /// Exposure of the tone mapping.
    pub exposure: f32,
    /// Seed of per-pixel dither.
    pub seed: u64,
}

/// What a camera ray sees: linear radiance, distance along the ray (metres) and class.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Linear radiance (before tone mapping).
    pub radiance: Rgb,
    /// Distance from the camera centre to the hit, metres; 0 if the ray escaped.
    pub depth: f64,
    /// Class id, or [`crate::data::UNKNOWN_PNG_LABEL`] if the ray escaped.
    pub class: u8,
}

impl Scene {
    /// The scene of `seed` (see the module docs for what it contains).
    pub fn generate(seed: u64) -> Scene {
        Builder::new(seed).build()
    }

    /// The nearest hit of `ray` and the index of the primitive hit.
    pub fn trace(&self, ray: &Ray) -> Option<(Hit, usize)> {
        let mut best = None;
        let mut t_max = f64::INFINITY;
        for (gi, g) in self.groups.iter().enumerate() {
            if gi > 0 && !g.bounds.hit(ray, t_max) {
                continue;
            }
            for i in g.start..g.end {
                if let Some(h) = self.prims[i].shape.intersect(ray, t_max) {
                    t_max = h.t;
                    best = Some((h, i));
                }
            }
        }
        best
    }

    /// Whether anything that casts shadows lies on `ray` before `dist`. Floor and ceiling
    /// planes are skipped: a segment between a point in the room and a light below the ceiling
    /// cannot cross them.
    pub fn occluded(&self, ray: &Ray, dist: f64) -> bool {
        for (gi, g) in self.groups.iter().enumerate() {
            if gi > 0 && !g.bounds.hit(ray, dist) {
                continue;
            }
            for p in &self.prims[g.start..g.end] {
                if !p.shadow || matches!(p.shape, Shape::Plane { .. }) {
                    continue;
                }
                if p.shape.intersect(ray, dist).is_some() {
                    return true;
                }
            }
        }
        false
    }

    /// What the camera sees along the unit direction `dir`, for a pixel `pixel_angle` radians
    /// wide (textures are filtered over its footprint `t pixel_angle / max(|n . d|, 0.1)`;
    /// shading in the module docs of [`super::appearance`]).
    pub fn sample(&self, dir: V3, pixel_angle: f64) -> Sample {
        let ray = Ray::new([0.0; 3], dir);
        let Some((hit, i)) = self.trace(&ray) else {
            return Sample {
                radiance: [0.0; 3],
                depth: 0.0,
                class: crate::data::UNKNOWN_PNG_LABEL,
            };
        };
        let prim = &self.prims[i];
        let footprint = hit.t * pixel_angle / dot(hit.n, dir).abs().max(0.1);
        let surf = self.materials[prim.material as usize].surface(&hit, footprint);
        let p = ray.at(hit.t);
        let n = hit.n;
        let up = -n[1] as f32;
        let mut light = self.ambient * (0.75 + 0.25 * up);
        let from = [p[0] + n[0] * 1e-4, p[1] + n[1] * 1e-4, p[2] + n[2] * 1e-4];
        for l in &self.lights {
            let to = sub(l.pos, from);
            let d = norm(to);
            let dir_l = scale(to, 1.0 / d);
            let cos = dot(n, dir_l);
            if cos <= 0.0 {
                continue;
            }
            if self.occluded(&Ray::new(from, dir_l), d) {
                continue;
            }
            let falloff = 1.0 / (1.0 + (d / FALLOFF_M).powi(2));
            light += l.intensity * (cos * falloff) as f32;
        }
        let radiance = [0, 1, 2].map(|c| surf.albedo[c] * light + surf.emission[c]);
        Sample {
            radiance,
            depth: hit.t,
            class: prim.class,
        }
    }
}

/// One box of a piece as [`Builder::cuboid`] takes it: local centre `(lx, lz)` in the piece's
/// frame, elevation range `[e0, e1]`, half sizes `(hx, hz)`, material.
type Part = ([f64; 2], [f64; 2], [f64; 2], u16);

struct Builder {
    rng: Rng,
    seed: u64,
    prims: Vec<Prim>,
    groups: Vec<Group>,
    materials: Vec<Material>,
    lights: Vec<Light>,
    cam_h: f64,
    height: f64,
    rects: Vec<Rect>,
    walls: Vec<WallSeg>,
    floor_used: Vec<Obb>,
    wall_used: Vec<WallSpan>,
    beams: Vec<Obb>,
    group_start: usize,
    wall_colour: Rgb,
    ceiling_colour: Rgb,
}

impl Builder {
    fn new(seed: u64) -> Self {
        Builder {
            rng: Rng::new(hash(seed, &[0x5CE7E])),
            seed,
            prims: Vec::new(),
            groups: Vec::new(),
            materials: Vec::new(),
            lights: Vec::new(),
            cam_h: 1.5,
            height: 3.0,
            rects: Vec::new(),
            walls: Vec::new(),
            floor_used: Vec::new(),
            wall_used: Vec::new(),
            beams: Vec::new(),
            group_start: 0,
            wall_colour: [0.7; 3],
            ceiling_colour: [0.8; 3],
        }
    }

    fn y(&self, e: f64) -> f64 {
        self.cam_h - e
    }

    fn material(&mut self, base: Rgb, alt: Rgb, pattern: Pattern) -> u16 {
        let seed = self.rng.next_u64();
        self.materials.push(Material {
            base,
            alt,
            pattern,
            seed,
        });
        (self.materials.len() - 1) as u16
    }

    fn plain(&mut self, base: Rgb, amp: f32) -> u16 {
        self.material(base, base, Pattern::Plain { freq: 1.5, amp })
    }

    fn begin(&mut self) {
        self.group_start = self.prims.len();
    }

    fn end(&mut self) {
        let (start, end) = (self.group_start, self.prims.len());
        if start == end {
            return;
        }
        let bounds = self.prims[start..end]
            .iter()
            .fold(Aabb::EMPTY, |b, p| b.union(p.shape.bounds()));
        self.groups.push(Group { bounds, start, end });
    }

    fn push(&mut self, shape: Shape, class: u8, material: u16) {
        self.prims.push(Prim {
            shape,
            class,
            material,
            shadow: true,
        });
    }

    /// A box in `frame`: local centre `at = (lx, lz)`, elevation range `e = [e0, e1]`, half
    /// sizes `half = (hx, hz)`, turned with the frame.
    fn cuboid(
        &mut self,
        frame: &Frame,
        at: [f64; 2],
        e: [f64; 2],
        half: [f64; 2],
        class: u8,
        mat: u16,
    ) {
        let [hx, hz] = half;
        let [x, z] = frame.world(at[0], at[1]);
        let (ya, yb) = (self.y(e[1]), self.y(e[0]));
        self.push(
            Shape::cuboid(
                [x, (ya + yb) / 2.0, z],
                [hx, (yb - ya) / 2.0, hz],
                frame.yaw,
            ),
            class,
            mat,
        );
    }

    /// The boxes `parts` of one class in `frame` ([`Builder::cuboid`] of each, in order).
    fn cuboids(&mut self, frame: &Frame, class: u8, parts: &[Part]) {
        for &(at, e, half, mat) in parts {
            self.cuboid(frame, at, e, half, class, mat);
        }
    }

    /// An upright cylinder in `frame`: local centre `at = (lx, lz)`, radius `r`, elevation
    /// range `e = [e0, e1]`.
    fn cylinder(&mut self, frame: &Frame, at: [f64; 2], r: f64, e: [f64; 2], class: u8, mat: u16) {
        let [x, z] = frame.world(at[0], at[1]);
        self.push(
            Shape::Cylinder {
                x,
                z,
                r,
                y0: self.y(e[1]),
                y1: self.y(e[0]),
            },
            class,
            mat,
        );
    }

    fn build(mut self) -> Scene {
        self.room();
        self.structure();
        self.beams();
        self.lights();
        self.columns();
        self.doors();
        self.windows();
        self.boards();
        self.bookcases();
        self.sofas();
        self.tables();
        self.single_chairs();
        self.floor_clutter();
        self.wall_clutter();
        let ambient = self.rng.uniform(0.22, 0.38) as f32;
        let exposure = self.rng.uniform(1.3, 1.9) as f32;
        Scene {
            prims: self.prims,
            groups: self.groups,
            materials: self.materials,
            lights: self.lights,
            camera_height: self.cam_h,
            room_height: self.height,
            footprint: self.rects,
            walls: self.walls,
            ambient,
            exposure,
            seed: hash(self.seed, &[0xD17E]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::class::*;
    use super::*;
    use crate::data::CLASSES;

    #[test]
    fn class_ids_follow_classes() {
        assert_eq!(ALL.len(), CLASSES.len());
        for (k, (name, id)) in ALL.into_iter().enumerate() {
            assert_eq!((CLASSES[id as usize], id as usize), (name, k));
        }
    }

    #[test]
    fn scenes_keep_the_camera_inside_and_clear() {
        for seed in 0..40 {
            let s = Scene::generate(seed);
            assert!(
                s.footprint.iter().any(|q| q.contains(0.0, 0.0, 0.59)),
                "seed {seed}"
            );
            assert!((1.2..=1.7).contains(&s.camera_height));
            assert!(!s.lights.is_empty() && s.lights.len() <= MAX_LIGHTS);
            // No primitive other than ceiling-level ones contains the camera.
            for p in &s.prims {
                if let Shape::Box { .. } | Shape::Cylinder { .. } = p.shape {
                    let b = p.shape.bounds();
                    let inside = (0..3).all(|a| b.lo[a] < 0.0 && b.hi[a] > 0.0);
                    assert!(!inside, "seed {seed}: camera inside {p:?}");
                }
            }
        }
    }
}
