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

use super::appearance::{mix, srgb, tint, vary, Material, Pattern, Rgb, FALLOFF_M};
use super::geometry::{dot, norm, scale, sub, Aabb, Hit, Ray, Shape, V3};
use crate::data::rng::{hash, Rng};

pub mod class {
    //! Class ids in [`crate::data::CLASSES`] order: one constant per class, named as the class.
    #![allow(missing_docs)]
    pub const BEAM: u8 = 0;
    pub const BOARD: u8 = 1;
    pub const BOOKCASE: u8 = 2;
    pub const CEILING: u8 = 3;
    pub const CHAIR: u8 = 4;
    pub const CLUTTER: u8 = 5;
    pub const COLUMN: u8 = 6;
    pub const DOOR: u8 = 7;
    pub const FLOOR: u8 = 8;
    pub const SOFA: u8 = 9;
    pub const TABLE: u8 = 10;
    pub const WALL: u8 = 11;
    pub const WINDOW: u8 = 12;
}
use class::*;

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

/// A floor-plan footprint: a rectangle of half sizes `h` turned by `yaw` around `c` (x, z).
#[derive(Clone, Copy, Debug)]
struct Obb {
    c: [f64; 2],
    h: [f64; 2],
    yaw: f64,
}

impl Obb {
    /// Local axes in (x, z): local x -> (cos, -sin), local z -> (sin, cos).
    fn axes(&self) -> [[f64; 2]; 2] {
        let (s, c) = self.yaw.sin_cos();
        [[c, -s], [s, c]]
    }
    fn corners(&self) -> [[f64; 2]; 4] {
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
    fn grown(&self, m: f64) -> Obb {
        Obb {
            h: [self.h[0] + m, self.h[1] + m],
            ..*self
        }
    }
    /// Separating-axis test of two rectangles.
    fn overlaps(&self, other: &Obb) -> bool {
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
    fn distance_to_origin(&self) -> f64 {
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
struct Frame {
    x: f64,
    z: f64,
    yaw: f64,
}

impl Frame {
    fn world(&self, lx: f64, lz: f64) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        [self.x + c * lx + s * lz, self.z - s * lx + c * lz]
    }
    fn sub(&self, lx: f64, lz: f64, yaw: f64) -> Frame {
        let [x, z] = self.world(lx, lz);
        Frame {
            x,
            z,
            yaw: self.yaw + yaw,
        }
    }
}

/// A reserved stretch of wall: wall index, `[s0, s1]` along it, elevations `[e0, e1]`.
type WallSpan = (usize, f64, f64, f64, f64);

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

    /// A box in `frame`: local centre `(lx, lz)`, elevation range `[e0, e1]`, half sizes
    /// `(hx, hz)`, extra yaw.
    #[allow(clippy::too_many_arguments)]
    fn cuboid(
        &mut self,
        frame: &Frame,
        lx: f64,
        lz: f64,
        e: [f64; 2],
        hx: f64,
        hz: f64,
        class: u8,
        mat: u16,
    ) {
        let [x, z] = frame.world(lx, lz);
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

    #[allow(clippy::too_many_arguments)]
    fn cylinder(
        &mut self,
        frame: &Frame,
        lx: f64,
        lz: f64,
        r: f64,
        e: [f64; 2],
        class: u8,
        mat: u16,
    ) {
        let [x, z] = frame.world(lx, lz);
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

    /// Floor plan, camera position, walls (step 1 of the module docs).
    fn room(&mut self) {
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

    fn inside(&self, x: f64, z: f64) -> bool {
        self.rects.iter().any(|q| q.contains(x, z, -1e-9))
    }

    /// Floor, ceiling, walls and their materials (group 0).
    fn structure(&mut self) {
        self.begin();
        let r = &mut self.rng;
        let floor_kind = r.below(4);
        let (base, alt, pattern) = match floor_kind {
            0 => {
                let c = *r.pick(&[
                    srgb(200, 190, 170),
                    srgb(165, 165, 160),
                    srgb(220, 218, 210),
                    srgb(170, 105, 75),
                ]);
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
                let c = *r.pick(&[srgb(150, 100, 60), srgb(185, 140, 90), srgb(110, 72, 45)]);
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
                let c = *r.pick(&[
                    srgb(90, 90, 100),
                    srgb(60, 72, 110),
                    srgb(115, 62, 62),
                    srgb(80, 100, 80),
                    srgb(130, 120, 110),
                ]);
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
        let floor = self.material(base, alt, pattern);
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
        let ceiling = self.material(ceiling_colour, tint(ceiling_colour, 0.75), ceiling_pattern);
        let r = &mut self.rng;
        let wall_colour = vary(
            *r.pick(&[
                srgb(230, 228, 220),
                srgb(225, 218, 198),
                srgb(200, 205, 212),
                srgb(212, 225, 212),
                srgb(235, 224, 196),
                srgb(190, 200, 218),
                srgb(215, 200, 190),
            ]),
            r,
            0.05,
        );
        let wall = if r.chance(0.2) {
            // Painted concrete blocks: the wall colour with slightly darker mortar.
            self.material(wall_colour, tint(wall_colour, 0.8), Pattern::Blocks)
        } else {
            self.plain(wall_colour, 0.06)
        };
        self.wall_colour = wall_colour;
        self.ceiling_colour = ceiling_colour;
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

    /// Ceiling beams spanning one rectangle of the plan.
    fn beams(&mut self) {
        if !self.rng.chance(0.35) {
            return;
        }
        let n = self.rng.int(1, 2);
        let colour = if self.rng.chance(0.5) {
            tint(self.ceiling_colour, 0.92)
        } else {
            vary(srgb(175, 175, 170), &mut self.rng, 0.06)
        };
        let mat = self.plain(colour, 0.12);
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
            self.cuboid(&frame, 0.0, 0.0, e, h[0], h[1], BEAM, mat);
            self.end();
        }
    }

    /// Ceiling light panels and their point lights, on a ~3 m grid per rectangle.
    fn lights(&mut self) {
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
            self.cuboid(&frame, 0.0, 0.0, e, half[0], half[1], CEILING, mat);
            self.prims.last_mut().expect("just pushed").shadow = false;
            self.end();
            self.lights.push(Light {
                pos: [x, self.y(self.height - 0.12), z],
                intensity,
            });
            placed += 1;
        }
    }

    /// Whether the wall stretch is free.
    fn wall_free(&self, w: usize, s: [f64; 2], e: [f64; 2]) -> bool {
        self.wall_used.iter().all(|&(wi, s0, s1, e0, e1)| {
            wi != w || s[1] <= s0 || s[0] >= s1 || e[1] <= e0 || e[0] >= e1
        })
    }

    /// Whether a floor rectangle fits: inside one plan rectangle, clear of the camera and of
    /// everything already placed.
    fn floor_free(&self, obb: &Obb) -> bool {
        let corners = obb.corners();
        let inside = self
            .rects
            .iter()
            .any(|q| corners.iter().all(|c| q.contains(c[0], c[1], 0.0)));
        inside
            && obb.distance_to_origin() >= CAMERA_CLEARANCE_M
            && self.floor_used.iter().all(|u| !u.overlaps(obb))
    }

    /// A random wall, weighted by length, and a stretch `[s0, s1]` of length `width` on it
    /// (with `margin` to its ends), or `None` if the wall is too short.
    fn wall_spot(&mut self, width: f64, margin: f64) -> Option<(usize, f64)> {
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
    fn against_wall(&mut self, hx: f64, hz: f64, e: [f64; 2], tries: usize) -> Option<Frame> {
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
    fn on_wall(&mut self, width: f64, e: [f64; 2], tries: usize) -> Option<(Frame, usize, f64)> {
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

    fn columns(&mut self) {
        if !self.rng.chance(0.4) {
            return;
        }
        let n = self.rng.int(1, 3);
        let colour = if self.rng.chance(0.5) {
            tint(self.wall_colour, 0.9)
        } else {
            vary(srgb(170, 170, 165), &mut self.rng, 0.08)
        };
        let mat = self.plain(colour, 0.1);
        let e = [0.0, self.height];
        for _ in 0..n {
            let half = self.rng.uniform(0.15, 0.32);
            let frame = if self.rng.chance(0.7) {
                // Half sunk into a wall.
                self.against_wall(half, half / 2.0, e, 20)
                    .map(|f| f.sub(0.0, -half / 2.0, 0.0))
            } else {
                let mut found = None;
                for _ in 0..20 {
                    let q = *self.rng.pick(&self.rects.clone());
                    let c = [
                        self.rng.uniform(q.x0 + 1.0, q.x1 - 1.0),
                        self.rng.uniform(q.z0 + 1.0, q.z1 - 1.0),
                    ];
                    let obb = Obb {
                        c,
                        h: [half, half],
                        yaw: 0.0,
                    };
                    if c[0].is_finite() && c[1].is_finite() && self.floor_free(&obb) {
                        self.floor_used.push(obb.grown(0.3));
                        found = Some(Frame {
                            x: c[0],
                            z: c[1],
                            yaw: 0.0,
                        });
                        break;
                    }
                }
                found
            };
            if let Some(f) = frame {
                self.begin();
                self.cuboid(&f, 0.0, 0.0, e, half, half, COLUMN, mat);
                self.end();
            }
        }
    }

    fn doors(&mut self) {
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
            let leaf = *r.pick(&[
                srgb(140, 92, 52),
                srgb(190, 150, 100),
                srgb(150, 155, 162),
                srgb(62, 82, 122),
                srgb(222, 220, 214),
                srgb(140, 42, 36),
            ]);
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
            // Leaf: 4 cm thick, 2 cm proud of the wall; frame: 3 cm proud.
            self.cuboid(&f, 0.0, 0.0, [0.0, top], hw, 0.02, DOOR, leaf_mat);
            self.cuboid(
                &f,
                -hw - fw / 2.0,
                0.0,
                [0.0, top + fw],
                fw / 2.0,
                0.03,
                DOOR,
                frame_mat,
            );
            self.cuboid(
                &f,
                hw + fw / 2.0,
                0.0,
                [0.0, top + fw],
                fw / 2.0,
                0.03,
                DOOR,
                frame_mat,
            );
            self.cuboid(
                &f,
                0.0,
                0.0,
                [top, top + fw],
                hw + fw,
                0.03,
                DOOR,
                frame_mat,
            );
            let handles: &[f64] = if double { &[-0.08, 0.08] } else { &[hw - 0.1] };
            for &hx in handles {
                self.cuboid(&f, hx, 0.04, [1.0, 1.04], 0.06, 0.02, DOOR, handle_mat);
            }
            self.end();
        }
    }

    fn windows(&mut self) {
        let corridor = self.rects.len() == 1
            && (self.rects[0].x1 - self.rects[0].x0).min(self.rects[0].z1 - self.rects[0].z0) < 2.7;
        let n = if corridor {
            self.rng.int(0, 1)
        } else {
            self.rng.int(0, 4)
        };
        let frame_colour = *self.rng.pick(&[
            srgb(232, 232, 230),
            srgb(160, 165, 172),
            srgb(40, 40, 42),
            srgb(120, 82, 50),
        ]);
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
            self.cuboid(&f, 0.0, 0.0, [sill, top], width / 2.0, 0.02, WINDOW, mat);
            // The sill belongs to the wall.
            self.cuboid(
                &f,
                0.0,
                0.06,
                [sill - 0.04, sill],
                width / 2.0 + 0.05,
                0.06,
                WALL,
                sill_mat,
            );
            self.end();
        }
    }

    fn boards(&mut self) {
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
                    *r.pick(&[srgb(30, 60, 160), srgb(170, 30, 30), srgb(25, 25, 25)]),
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
            self.cuboid(&f, 0.0, 0.0, [bottom, top], hw, 0.015, BOARD, mat);
            self.cuboid(&f, 0.0, 0.0, [bottom - t, bottom], hw + t, 0.02, BOARD, rim);
            self.cuboid(&f, 0.0, 0.0, [top, top + t], hw + t, 0.02, BOARD, rim);
            self.cuboid(
                &f,
                -hw - t / 2.0,
                0.0,
                [bottom, top],
                t / 2.0,
                0.02,
                BOARD,
                rim,
            );
            self.cuboid(
                &f,
                hw + t / 2.0,
                0.0,
                [bottom, top],
                t / 2.0,
                0.02,
                BOARD,
                rim,
            );
            // A marker tray on whiteboards.
            if kind == 0 {
                self.cuboid(
                    &f,
                    0.0,
                    0.04,
                    [bottom - 0.05, bottom - 0.03],
                    hw * 0.6,
                    0.04,
                    BOARD,
                    rim,
                );
            }
            self.end();
        }
    }

    fn bookcases(&mut self) {
        let n = self.rng.int(0, 3);
        let wood = *self.rng.pick(&[
            srgb(150, 105, 65),
            srgb(200, 170, 125),
            srgb(160, 162, 168),
            srgb(90, 60, 40),
            srgb(225, 225, 220),
        ]);
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
            self.cuboid(&f, 0.0, -hz + 0.01, [0.0, top], hx, 0.01, BOOKCASE, back);
            self.cuboid(
                &f,
                -hx + t / 2.0,
                0.0,
                [0.0, top],
                t / 2.0,
                hz,
                BOOKCASE,
                frame_mat,
            );
            self.cuboid(
                &f,
                hx - t / 2.0,
                0.0,
                [0.0, top],
                t / 2.0,
                hz,
                BOOKCASE,
                frame_mat,
            );
            self.cuboid(&f, 0.0, 0.0, [top - t, top], hx, hz, BOOKCASE, frame_mat);
            self.cuboid(&f, 0.0, 0.0, [0.0, 0.08], hx - t, hz, BOOKCASE, frame_mat);
            let shelves = ((top - 0.1) / self.rng.uniform(0.3, 0.4)).floor().max(1.0) as usize;
            let pitch = (top - t - 0.08) / shelves as f64;
            for k in 0..shelves {
                let e0 = 0.08 + k as f64 * pitch;
                if k > 0 {
                    self.cuboid(
                        &f,
                        0.0,
                        0.0,
                        [e0 - t / 2.0, e0 + t / 2.0],
                        hx - t,
                        hz,
                        BOOKCASE,
                        frame_mat,
                    );
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
                        0.0,
                        -recess / 2.0 + 0.0,
                        [b0, b1],
                        hx - t,
                        depth - 0.01,
                        BOOKCASE,
                        books,
                    );
                }
            }
            self.end();
        }
    }

    fn fabric(&mut self) -> Rgb {
        let c = *self.rng.pick(&[
            srgb(95, 70, 50),
            srgb(120, 120, 125),
            srgb(50, 65, 110),
            srgb(140, 45, 40),
            srgb(60, 95, 70),
            srgb(35, 35, 38),
            srgb(190, 175, 150),
        ]);
        vary(c, &mut self.rng, 0.08)
    }

    fn sofas(&mut self) {
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
            let mat = self.material(
                c,
                c,
                Pattern::Fabric {
                    freq: 70.0,
                    amp: 0.12,
                },
            );
            let cushion = self.material(
                tint(c, 1.1),
                c,
                Pattern::Fabric {
                    freq: 70.0,
                    amp: 0.12,
                },
            );
            let feet = self.plain(srgb(40, 35, 30), 0.05);
            let arm = 0.12;
            self.begin();
            self.cuboid(&f, 0.0, 0.0, [0.06, seat - 0.1], hx, hz, SOFA, mat);
            self.cuboid(
                &f,
                0.0,
                -hz + 0.1,
                [seat - 0.1, back_top],
                hx,
                0.1,
                SOFA,
                mat,
            );
            self.cuboid(
                &f,
                -hx + arm / 2.0,
                0.05,
                [seat - 0.1, seat + 0.15],
                arm / 2.0,
                hz - 0.05,
                SOFA,
                mat,
            );
            self.cuboid(
                &f,
                hx - arm / 2.0,
                0.05,
                [seat - 0.1, seat + 0.15],
                arm / 2.0,
                hz - 0.05,
                SOFA,
                mat,
            );
            let cushions = if hx > 0.95 { 3 } else { 2 };
            let inner = hx - arm;
            let cw = 2.0 * inner / cushions as f64;
            for k in 0..cushions {
                let x = -inner + cw * (k as f64 + 0.5);
                self.cuboid(
                    &f,
                    x,
                    0.08,
                    [seat - 0.1, seat],
                    cw / 2.0 - 0.01,
                    hz - 0.16,
                    SOFA,
                    cushion,
                );
            }
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                self.cuboid(
                    &f,
                    sx * (hx - 0.06),
                    sz * (hz - 0.06),
                    [0.0, 0.06],
                    0.025,
                    0.025,
                    SOFA,
                    feet,
                );
            }
            self.end();
        }
    }

    /// One chair at `f` facing local +z (seat centre at the frame origin).
    fn chair(&mut self, f: &Frame, seat_mat: u16, leg_mat: u16, office: bool) {
        let hs = 0.23;
        let seat = 0.46;
        self.begin();
        self.cuboid(f, 0.0, 0.0, [seat - 0.05, seat], hs, hs, CHAIR, seat_mat);
        self.cuboid(
            f,
            0.0,
            -hs + 0.02,
            [seat + 0.08, seat + 0.5],
            hs - 0.01,
            0.02,
            CHAIR,
            seat_mat,
        );
        if office {
            self.cylinder(f, 0.0, 0.0, 0.025, [0.08, seat - 0.05], CHAIR, leg_mat);
            self.cylinder(f, 0.0, 0.0, 0.3, [0.03, 0.08], CHAIR, leg_mat);
            // Arm rests.
            for sx in [-1.0, 1.0] {
                self.cuboid(
                    f,
                    sx * (hs + 0.02),
                    0.0,
                    [seat + 0.16, seat + 0.19],
                    0.025,
                    0.14,
                    CHAIR,
                    leg_mat,
                );
                self.cuboid(
                    f,
                    sx * (hs + 0.02),
                    0.0,
                    [seat, seat + 0.16],
                    0.01,
                    0.015,
                    CHAIR,
                    leg_mat,
                );
            }
        } else {
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                let top = if sz < 0.0 { seat + 0.1 } else { seat - 0.05 };
                self.cuboid(
                    f,
                    sx * (hs - 0.02),
                    sz * (hs - 0.02),
                    [0.0, top],
                    0.015,
                    0.015,
                    CHAIR,
                    leg_mat,
                );
            }
        }
        self.end();
    }

    fn chair_style(&mut self) -> (u16, u16, bool) {
        let c = self.fabric();
        let seat = self.material(
            c,
            c,
            Pattern::Fabric {
                freq: 80.0,
                amp: 0.1,
            },
        );
        let leg_c = *self
            .rng
            .pick(&[srgb(40, 40, 42), srgb(170, 172, 178), srgb(120, 85, 55)]);
        let legs = self.plain(leg_c, 0.03);
        (seat, legs, self.rng.chance(0.5))
    }

    fn tables(&mut self) {
        let area: f64 = self.rects.iter().map(Rect::area).sum();
        let n = self.rng.int(0, ((area / 10.0) as usize + 1).min(5));
        let (chair_seat, chair_legs, office) = self.chair_style();
        let r = &mut self.rng;
        let top_c = *r.pick(&[
            srgb(160, 115, 70),
            srgb(210, 185, 145),
            srgb(235, 235, 230),
            srgb(120, 122, 128),
            srgb(70, 50, 35),
        ]);
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
            let mut placed = None;
            for _ in 0..25 {
                let q = *self.rng.pick(&self.rects.clone());
                let c = [self.rng.uniform(q.x0, q.x1), self.rng.uniform(q.z0, q.z1)];
                let obb = Obb {
                    c,
                    h: [gx, gz],
                    yaw,
                };
                if self.floor_free(&obb) {
                    self.floor_used.push(obb.grown(0.05));
                    placed = Some(Frame {
                        x: c[0],
                        z: c[1],
                        yaw,
                    });
                    break;
                }
            }
            let Some(f) = placed else {
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
            self.cuboid(&f, 0.0, 0.0, [height - t, height], hx, hz, TABLE, top_mat);
            if self.rng.chance(0.8) {
                for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                    self.cuboid(
                        &f,
                        sx * (hx - 0.06),
                        sz * (hz - 0.06),
                        [0.0, height - t],
                        0.025,
                        0.025,
                        TABLE,
                        leg_mat,
                    );
                }
            } else {
                // Panel ends (desk style).
                for sx in [-1.0, 1.0] {
                    self.cuboid(
                        &f,
                        sx * (hx - 0.03),
                        0.0,
                        [0.0, height - t],
                        0.015,
                        hz - 0.04,
                        TABLE,
                        leg_mat,
                    );
                }
            }
            self.end();
            self.table_clutter(&f, hx, hz, height);
            // Chairs facing the table, pulled out 0.15-0.45 m, turned +-20 degrees.
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
                self.chair(&cf, chair_seat, chair_legs, office);
            }
        }
    }

    /// Monitors, laptops, papers, mugs, books on a table top.
    fn table_clutter(&mut self, f: &Frame, hx: f64, hz: f64, height: f64) {
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
                    self.cuboid(
                        &item,
                        0.0,
                        0.0,
                        [height, height + 0.015],
                        0.1,
                        0.08,
                        CLUTTER,
                        body,
                    );
                    self.cuboid(
                        &item,
                        0.0,
                        -0.02,
                        [height, height + 0.12],
                        0.025,
                        0.015,
                        CLUTTER,
                        body,
                    );
                    self.cuboid(
                        &item,
                        0.0,
                        0.0,
                        [height + 0.1, height + 0.1 + w * 1.2],
                        w,
                        0.02,
                        CLUTTER,
                        screen,
                    );
                }
                1 => {
                    let c = *self.rng.pick(&[srgb(40, 40, 44), srgb(190, 192, 196)]);
                    let m = self.plain(c, 0.03);
                    self.cuboid(
                        &item,
                        0.0,
                        0.0,
                        [height, height + 0.02],
                        0.17,
                        0.12,
                        CLUTTER,
                        m,
                    );
                    self.cuboid(
                        &item,
                        0.0,
                        -0.12,
                        [height + 0.02, height + 0.24],
                        0.17,
                        0.006,
                        CLUTTER,
                        m,
                    );
                }
                2 => {
                    let m = self.plain(srgb(240, 240, 235), 0.02);
                    self.cuboid(
                        &item,
                        0.0,
                        0.0,
                        [height, height + 0.01],
                        0.105,
                        0.15,
                        CLUTTER,
                        m,
                    );
                }
                3 => {
                    let c = vary(srgb(200, 60, 50), &mut self.rng, 0.3);
                    let m = self.plain(c, 0.05);
                    self.cylinder(&item, 0.0, 0.0, 0.04, [height, height + 0.1], CLUTTER, m);
                }
                _ => {
                    let c = vary(srgb(60, 90, 150), &mut self.rng, 0.3);
                    let m = self.plain(c, 0.05);
                    let h = self.rng.uniform(0.03, 0.12);
                    self.cuboid(
                        &item,
                        0.0,
                        0.0,
                        [height, height + h],
                        0.12,
                        0.09,
                        CLUTTER,
                        m,
                    );
                }
            }
            self.end();
        }
    }

    fn single_chairs(&mut self) {
        let n = self.rng.int(0, 3);
        let (seat, legs, office) = self.chair_style();
        for _ in 0..n {
            for _ in 0..15 {
                let q = *self.rng.pick(&self.rects.clone());
                let c = [self.rng.uniform(q.x0, q.x1), self.rng.uniform(q.z0, q.z1)];
                let yaw = self.rng.uniform(0.0, 2.0 * PI);
                let obb = Obb {
                    c,
                    h: [0.3, 0.3],
                    yaw,
                };
                if self.floor_free(&obb) {
                    self.floor_used.push(obb.grown(0.05));
                    let f = Frame {
                        x: c[0],
                        z: c[1],
                        yaw,
                    };
                    self.chair(&f, seat, legs, office);
                    break;
                }
            }
        }
    }

    fn floor_clutter(&mut self) {
        let n = self.rng.int(2, 10);
        for _ in 0..n {
            let kind = self.rng.below(5);
            match kind {
                // Cabinet against a wall.
                0 => {
                    let hx = self.rng.uniform(0.2, 0.5);
                    let hz = self.rng.uniform(0.2, 0.3);
                    let top = self.rng.uniform(0.7, 1.3);
                    let Some(f) = self.against_wall(hx, hz, [0.0, top], 10) else {
                        continue;
                    };
                    let c = vary(
                        *self.rng.pick(&[
                            srgb(180, 182, 186),
                            srgb(210, 200, 175),
                            srgb(90, 92, 98),
                        ]),
                        &mut self.rng,
                        0.06,
                    );
                    let m = self.plain(c, 0.04);
                    let handle = self.plain(tint(c, 0.5), 0.02);
                    self.begin();
                    self.cuboid(&f, 0.0, 0.0, [0.0, top], hx, hz, CLUTTER, m);
                    let drawers = self.rng.int(1, 4);
                    for k in 0..drawers {
                        let e = top * (k as f64 + 0.5) / drawers as f64;
                        self.cuboid(
                            &f,
                            0.0,
                            hz + 0.01,
                            [e - 0.01, e + 0.01],
                            hx * 0.3,
                            0.01,
                            CLUTTER,
                            handle,
                        );
                    }
                    self.end();
                }
                // Boxes, bins, plants: free-standing.
                _ => {
                    let r = self.rng.uniform(0.15, 0.35);
                    let mut spot = None;
                    for _ in 0..15 {
                        let q = *self.rng.pick(&self.rects.clone());
                        let c = [self.rng.uniform(q.x0, q.x1), self.rng.uniform(q.z0, q.z1)];
                        let yaw = self.rng.uniform(0.0, PI);
                        let obb = Obb { c, h: [r, r], yaw };
                        if self.floor_free(&obb) {
                            self.floor_used.push(obb.grown(0.05));
                            spot = Some(Frame {
                                x: c[0],
                                z: c[1],
                                yaw,
                            });
                            break;
                        }
                    }
                    let Some(f) = spot else {
                        continue;
                    };
                    self.begin();
                    match kind {
                        1 => {
                            let c = vary(srgb(170, 130, 85), &mut self.rng, 0.1);
                            let m = self.plain(c, 0.1);
                            let h = self.rng.uniform(0.2, 0.6);
                            self.cuboid(&f, 0.0, 0.0, [0.0, h], r, r * 0.8, CLUTTER, m);
                            if self.rng.chance(0.4) {
                                let h2 = h + self.rng.uniform(0.15, 0.4);
                                let g = f.sub(0.0, 0.0, self.rng.uniform(-0.3, 0.3));
                                self.cuboid(&g, 0.0, 0.0, [h, h2], r * 0.7, r * 0.6, CLUTTER, m);
                            }
                        }
                        2 => {
                            let c = *self.rng.pick(&[
                                srgb(60, 90, 160),
                                srgb(80, 80, 85),
                                srgb(40, 120, 60),
                            ]);
                            let m = self.plain(c, 0.05);
                            let h = self.rng.uniform(0.3, 0.6);
                            self.cylinder(&f, 0.0, 0.0, r * 0.7, [0.0, h], CLUTTER, m);
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
                            self.cylinder(&f, 0.0, 0.0, r * 0.6, [0.0, h], CLUTTER, pot);
                            let top = h + self.rng.uniform(0.4, 1.0);
                            self.cylinder(&f, 0.0, 0.0, r, [h, top], CLUTTER, leaves);
                        }
                        _ => {
                            // A printer / appliance.
                            let m = self.plain(srgb(215, 215, 210), 0.03);
                            let d = self.plain(srgb(50, 50, 52), 0.03);
                            self.cuboid(&f, 0.0, 0.0, [0.0, 0.7], r, r, CLUTTER, d);
                            self.cuboid(&f, 0.0, 0.0, [0.7, 1.0], r, r, CLUTTER, m);
                        }
                    }
                    self.end();
                }
            }
        }
    }

    /// Pictures, posters, radiators and air conditioners on the walls.
    fn wall_clutter(&mut self) {
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
                        *self.rng.pick(&[
                            srgb(180, 60, 50),
                            srgb(60, 120, 170),
                            srgb(220, 200, 120),
                            srgb(90, 140, 80),
                        ]),
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
                    self.cuboid(&f, 0.0, 0.0, e, width / 2.0, 0.015, CLUTTER, m);
                    self.cuboid(
                        &f,
                        0.0,
                        0.0,
                        [e[0] - 0.02, e[0]],
                        width / 2.0 + 0.02,
                        0.02,
                        CLUTTER,
                        frame,
                    );
                    self.cuboid(
                        &f,
                        0.0,
                        0.0,
                        [e[1], e[1] + 0.02],
                        width / 2.0 + 0.02,
                        0.02,
                        CLUTTER,
                        frame,
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
                    self.cuboid(&f, 0.0, 0.0, e, width / 2.0, 0.05, CLUTTER, m);
                }
                _ => {
                    let m = self.plain(srgb(235, 235, 232), 0.03);
                    self.cuboid(&f, 0.0, 0.0, e, width / 2.0, 0.11, CLUTTER, m);
                }
            }
            self.end();
        }
    }
}

/// The walls of a plan made of one rectangle, or of two sharing part of a side (an L): the
/// outline of the union, split into axis-aligned segments, each with its inward side.
fn walls_of(rects: &[Rect]) -> Vec<WallSeg> {
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
    use crate::data::CLASSES;

    #[test]
    fn class_ids_follow_classes() {
        let ids = [
            ("beam", BEAM),
            ("board", BOARD),
            ("bookcase", BOOKCASE),
            ("ceiling", CEILING),
            ("chair", CHAIR),
            ("clutter", CLUTTER),
            ("column", COLUMN),
            ("door", DOOR),
            ("floor", FLOOR),
            ("sofa", SOFA),
            ("table", TABLE),
            ("wall", WALL),
            ("window", WINDOW),
        ];
        for (name, id) in ids {
            assert_eq!(CLASSES[id as usize], name);
        }
    }

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
