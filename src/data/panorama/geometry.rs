//! Analytic ray / primitive intersection for the procedural scenes.
//!
//! World frame (shared with [`crate::camera`]): x right, y **down**, z forward, metres; the
//! panorama's camera centre is the origin. Every primitive is one of four shapes whose
//! intersection has a closed form:
//!
//! - [`Shape::Plane`]: the horizontal plane `y = y0` (floor, ceiling): `t = (y0 - o_y) / d_y`;
//! - [`Shape::Wall`]: a vertical rectangle on `coord[axis] = at`, bounded in the other horizontal
//!   coordinate (the floor and ceiling bound it vertically);
//! - [`Shape::Box`]: a box turned by `yaw` about the vertical axis through its centre; the ray is
//!   moved into the box frame and clipped against three slabs (Kay and Kajiya 1986);
//! - [`Shape::Cylinder`]: a vertical capped cylinder, `|(x, z) - c|^2 = r^2` for the side plus two
//!   discs.
//!
//! A box's yaw maps its local axes to the world as `x_w = cos(yaw) x_l + sin(yaw) z_l`,
//! `z_w = -sin(yaw) x_l + cos(yaw) z_l` (so local +z points along `(sin yaw, 0, cos yaw)`).

/// A 3-vector `[x, y, z]`.
pub type V3 = [f64; 3];

/// Smallest ray parameter accepted as a hit, in metres (rays start on surfaces for shadows).
pub const T_MIN: f64 = 1e-6;

/// `a + b`.
pub fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a - b`.
pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a s`.
pub fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// `a . b`.
pub fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `|a|`.
pub fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|` (`a` must be non-zero).
pub fn normalize(a: V3) -> V3 {
    scale(a, 1.0 / norm(a))
}

/// A ray `o + t d` with `|d| = 1` and its componentwise inverse direction (for slab tests).
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Origin.
    pub o: V3,
    /// Unit direction.
    pub d: V3,
    inv: V3,
}

impl Ray {
    /// A ray from `o` along the unit vector `d`.
    pub fn new(o: V3, d: V3) -> Self {
        Ray {
            o,
            d,
            inv: [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]],
        }
    }

    /// The point at parameter `t`.
    pub fn at(&self, t: f64) -> V3 {
        add(self.o, scale(self.d, t))
    }
}

/// An axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub lo: V3,
    /// Largest corner.
    pub hi: V3,
}

impl Aabb {
    /// The empty box (the identity of [`Aabb::union`]).
    pub const EMPTY: Aabb = Aabb {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };

    /// The smallest box holding both.
    pub fn union(self, other: Aabb) -> Aabb {
        let mut out = self;
        for a in 0..3 {
            out.lo[a] = out.lo[a].min(other.lo[a]);
            out.hi[a] = out.hi[a].max(other.hi[a]);
        }
        out
    }

    /// Whether the ray enters the box before `t_max` (slab test; IEEE infinities handle rays
    /// parallel to a slab).
    pub fn hit(&self, ray: &Ray, t_max: f64) -> bool {
        let (mut t0, mut t1) = (T_MIN, t_max);
        for a in 0..3 {
            let ta = (self.lo[a] - ray.o[a]) * ray.inv[a];
            let tb = (self.hi[a] - ray.o[a]) * ray.inv[a];
            let (near, far) = if ta < tb { (ta, tb) } else { (tb, ta) };
            // NaN (0 * inf for a ray inside a zero-width slab) compares false and is skipped.
            if near > t0 {
                t0 = near;
            }
            if far < t1 {
                t1 = far;
            }
            if t0 > t1 {
                return false;
            }
        }
        true
    }
}

/// A surface hit: distance, world normal facing the ray, and the point and normal axis in the
/// primitive's own frame (for textures).
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    /// Ray parameter (metres along the unit direction).
    pub t: f64,
    /// Unit world normal, facing the incoming ray (`n . d <= 0`).
    pub n: V3,
    /// Hit point in the primitive frame (box: relative to its centre, turned by `-yaw`;
    /// others: world).
    pub local: V3,
    /// Which local axis the surface is perpendicular to: 0 (x), 1 (y, horizontal surface),
    /// 2 (z); a cylinder's side reports 0.
    pub axis: u8,
}

/// The primitive shapes (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// The horizontal plane `y = y`.
    Plane {
        /// Height of the plane (y down).
        y: f64,
    },
    /// The vertical plane `coord[axis] = at` (`axis` 0 or 2), for the other horizontal coordinate
    /// in `[lo, hi]`.
    Wall {
        /// The coordinate the plane is perpendicular to: 0 (x) or 2 (z).
        axis: usize,
        /// Its value on the plane.
        at: f64,
        /// Lower end of the other horizontal coordinate.
        lo: f64,
        /// Upper end of the other horizontal coordinate.
        hi: f64,
    },
    /// A box with centre `c`, half sizes `h` (local x, y, z) turned by `yaw` (stored as its
    /// cosine and sine) about the vertical axis.
    Box {
        /// Centre.
        c: V3,
        /// Half sizes along the local axes.
        h: V3,
        /// `cos(yaw)`.
        cos: f64,
        /// `sin(yaw)`.
        sin: f64,
    },
    /// A vertical cylinder of radius `r` around `(x, z)`, between `y0 < y1`.
    Cylinder {
        /// Axis x.
        x: f64,
        /// Axis z.
        z: f64,
        /// Radius.
        r: f64,
        /// Top (smaller y, as y points down).
        y0: f64,
        /// Bottom.
        y1: f64,
    },
}

impl Shape {
    /// A box with centre `c`, half sizes `h` and yaw `yaw` (radians).
    pub fn cuboid(c: V3, h: V3, yaw: f64) -> Shape {
        Shape::Box {
            c,
            h,
            cos: yaw.cos(),
            sin: yaw.sin(),
        }
    }

    /// World bounds (infinite for planes and walls, which are never culled).
    pub fn bounds(&self) -> Aabb {
        match *self {
            Shape::Plane { .. } | Shape::Wall { .. } => Aabb {
                lo: [f64::NEG_INFINITY; 3],
                hi: [f64::INFINITY; 3],
            },
            Shape::Box { c, h, cos, sin } => {
                let ex = h[0] * cos.abs() + h[2] * sin.abs();
                let ez = h[0] * sin.abs() + h[2] * cos.abs();
                Aabb {
                    lo: [c[0] - ex, c[1] - h[1], c[2] - ez],
                    hi: [c[0] + ex, c[1] + h[1], c[2] + ez],
                }
            }
            Shape::Cylinder { x, z, r, y0, y1 } => Aabb {
                lo: [x - r, y0, z - r],
                hi: [x + r, y1, z + r],
            },
        }
    }

    /// The nearest hit with `T_MIN < t < t_max`, if any.
    pub fn intersect(&self, ray: &Ray, t_max: f64) -> Option<Hit> {
        match *self {
            Shape::Plane { y } => hit_plane(ray, t_max, y),
            Shape::Wall { axis, at, lo, hi } => hit_wall(ray, t_max, axis, at, [lo, hi]),
            Shape::Box { c, h, cos, sin } => hit_box(ray, t_max, c, h, [cos, sin]),
            Shape::Cylinder { x, z, r, y0, y1 } => hit_cylinder(ray, t_max, [x, z], r, [y0, y1]),
        }
    }
}

/// [`Shape::Plane`] `y`.
fn hit_plane(ray: &Ray, t_max: f64, y: f64) -> Option<Hit> {
    let t = (y - ray.o[1]) / ray.d[1];
    (t > T_MIN && t < t_max).then(|| Hit {
        t,
        n: [0.0, -ray.d[1].signum(), 0.0],
        local: ray.at(t),
        axis: 1,
    })
}

/// [`Shape::Wall`]: the plane `coord[axis] = at` for the other coordinate in `[lo, hi]`.
fn hit_wall(ray: &Ray, t_max: f64, axis: usize, at: f64, [lo, hi]: [f64; 2]) -> Option<Hit> {
    let t = (at - ray.o[axis]) / ray.d[axis];
    if !(t > T_MIN && t < t_max) {
        return None;
    }
    let p = ray.at(t);
    let other = 2 - axis;
    if p[other] < lo || p[other] > hi {
        return None;
    }
    let mut n = [0.0; 3];
    n[axis] = -ray.d[axis].signum();
    Some(Hit {
        t,
        n,
        local: p,
        axis: axis as u8,
    })
}

/// [`Shape::Box`] of centre `c` and half sizes `h`, turned by the angle of `[cos, sin]`: the slab
/// test in the box frame.
fn hit_box(ray: &Ray, t_max: f64, c: V3, h: V3, [cos, sin]: [f64; 2]) -> Option<Hit> {
    // Into the box frame: x_l = cos x_w - sin z_w, z_l = sin x_w + cos z_w.
    let (ox, oz) = (ray.o[0] - c[0], ray.o[2] - c[2]);
    let o = [cos * ox - sin * oz, ray.o[1] - c[1], sin * ox + cos * oz];
    let d = [
        cos * ray.d[0] - sin * ray.d[2],
        ray.d[1],
        sin * ray.d[0] + cos * ray.d[2],
    ];
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    let mut axis = 0;
    for a in 0..3 {
        if d[a] == 0.0 {
            if o[a].abs() > h[a] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d[a];
        let ta = (-h[a] - o[a]) * inv;
        let tb = (h[a] - o[a]) * inv;
        let (near, far) = if ta < tb { (ta, tb) } else { (tb, ta) };
        if near > t0 {
            t0 = near;
            axis = a;
        }
        t1 = t1.min(far);
    }
    if t0 > t1 || !(t0 > T_MIN && t0 < t_max) {
        return None;
    }
    let mut nl = [0.0; 3];
    nl[axis] = -d[axis].signum();
    // Back to the world: x_w = cos x_l + sin z_l, z_w = -sin x_l + cos z_l.
    let n = [cos * nl[0] + sin * nl[2], nl[1], -sin * nl[0] + cos * nl[2]];
    Some(Hit {
        t: t0,
        n,
        local: add(o, scale(d, t0)),
        axis: axis as u8,
    })
}

/// [`Shape::Cylinder`] of axis `(x, z)`, radius `r`, from `y0` to `y1`: its side (the near root
/// only) and its two caps, the nearest.
fn hit_cylinder(
    ray: &Ray,
    t_max: f64,
    [x, z]: [f64; 2],
    r: f64,
    [y0, y1]: [f64; 2],
) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let (ox, oz) = (ray.o[0] - x, ray.o[2] - z);
    let a = ray.d[0] * ray.d[0] + ray.d[2] * ray.d[2];
    if a > 0.0 {
        let b = ox * ray.d[0] + oz * ray.d[2];
        let c = ox * ox + oz * oz - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            // The near root only: rays start outside every cylinder.
            let t = (-b - disc.sqrt()) / a;
            if t > T_MIN && t < t_max {
                let p = ray.at(t);
                if p[1] >= y0 && p[1] <= y1 {
                    best = Some(Hit {
                        t,
                        n: [(p[0] - x) / r, 0.0, (p[2] - z) / r],
                        local: p,
                        axis: 0,
                    });
                }
            }
        }
    }
    for cap in [y0, y1] {
        let t = (cap - ray.o[1]) / ray.d[1];
        if t > T_MIN && t < best.map_or(t_max, |h| h.t) {
            let p = ray.at(t);
            let (dx, dz) = (p[0] - x, p[2] - z);
            if dx * dx + dz * dz <= r * r {
                best = Some(Hit {
                    t,
                    n: [0.0, -ray.d[1].signum(), 0.0],
                    local: p,
                    axis: 1,
                });
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed forms in f64 on metre-scale scenes are exact to ~1e-15 m; 1e-12 m leaves room for
    /// the few operations in between.
    const TOL: f64 = 1e-12;

    #[test]
    fn plane_and_wall_distances() {
        let down = Ray::new([0.0; 3], [0.0, 1.0, 0.0]);
        let floor = Shape::Plane { y: 1.5 };
        let h = floor.intersect(&down, f64::INFINITY).unwrap();
        assert!((h.t - 1.5).abs() < TOL);
        assert_eq!(h.n, [0.0, -1.0, 0.0]);
        let up = Ray::new([0.0; 3], [0.0, -1.0, 0.0]);
        assert!(floor.intersect(&up, f64::INFINITY).is_none());

        let d = normalize([1.0, 0.0, 1.0]);
        let wall = Shape::Wall {
            axis: 0,
            at: 2.0,
            lo: -1.0,
            hi: 1.0,
        };
        // Hits x = 2 at z = 2, outside [-1, 1].
        assert!(wall
            .intersect(&Ray::new([0.0; 3], d), f64::INFINITY)
            .is_none());
        let h = wall
            .intersect(&Ray::new([0.0; 3], [1.0, 0.0, 0.0]), f64::INFINITY)
            .unwrap();
        assert!((h.t - 2.0).abs() < TOL);
        assert_eq!(h.n, [-1.0, 0.0, 0.0]);
    }

    #[test]
    fn turned_box_matches_its_corners() {
        // A 2 x 2 x 2 box at z = 5 turned by 45 degrees presents an edge at z = 5 - sqrt(2).
        let b = Shape::cuboid([0.0, 0.0, 5.0], [1.0; 3], std::f64::consts::FRAC_PI_4);
        let h = b
            .intersect(&Ray::new([0.0; 3], [0.0, 0.0, 1.0]), f64::INFINITY)
            .unwrap();
        assert!((h.t - (5.0 - 2f64.sqrt())).abs() < 1e-9);
        let bounds = b.bounds();
        assert!((bounds.lo[2] - (5.0 - 2f64.sqrt())).abs() < TOL);
        // A ray just past the edge misses.
        let miss = Ray::new([1.5, 0.0, 0.0], [0.0, 0.0, 1.0]);
        assert!(b.intersect(&miss, f64::INFINITY).is_none());
        assert!(!bounds.hit(&miss, f64::INFINITY));
        // The far face is never reported from outside; t_max cuts.
        assert!(b
            .intersect(&Ray::new([0.0; 3], [0.0, 0.0, 1.0]), 3.0)
            .is_none());
    }

    #[test]
    fn cylinder_side_and_cap() {
        let c = Shape::Cylinder {
            x: 0.0,
            z: 3.0,
            r: 0.5,
            y0: 0.0,
            y1: 1.0,
        };
        let h = c
            .intersect(&Ray::new([0.0, 0.5, 0.0], [0.0, 0.0, 1.0]), f64::INFINITY)
            .unwrap();
        assert!((h.t - 2.5).abs() < TOL);
        assert!((h.n[2] + 1.0).abs() < TOL);
        // From above the cap.
        let h = c
            .intersect(&Ray::new([0.0, -2.0, 3.2], [0.0, 1.0, 0.0]), f64::INFINITY)
            .unwrap();
        assert!((h.t - 2.0).abs() < TOL);
        assert_eq!(h.axis, 1);
    }
}
