//! View synthesis: perspective and fisheye images (with depth, labels and a validity mask)
//! rendered from an equirectangular [`Panorama`] for any [`Camera`], and rectified views
//! (a fisheye image re-projected to a pinhole camera).
//!
//! # Conventions
//!
//! - Camera pixels and rays as in [`crate::camera`]: pixel `(u, v)` = (column, row), the centre
//!   of the top-left pixel at `(0, 0)`; camera rays x right, y down, z forward.
//! - An [`Orientation`] turns camera rays into panorama (world) directions:
//!   `R = R_y(yaw) R_x(pitch) R_z(roll)` with
//!
//!   ```text
//!   R_y(a) = [[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]]   yaw: + turns right (to +x)
//!   R_x(a) = [[1, 0, 0], [0, cos a, -sin a], [0, sin a, cos a]]   pitch: + looks up (to -y)
//!   R_z(a) = [[cos a, -sin a, 0], [sin a, cos a, 0], [0, 0, 1]]   roll: + turns the camera
//!                                                                 clockwise seen from behind
//!   ```
//!
//!   so the optical axis looks along `R (0, 0, 1) = (cos p sin y, -sin p, cos p cos y)`: at
//!   panorama longitude `yaw` and latitude `pitch`. Radians everywhere.
//! - **Random orientations** ([`ViewSampling`]): the paper synthesises its fisheye images "in
//!   different orientations" without saying how; we draw yaw uniformly in `[-pi, pi)` and pitch
//!   and roll uniformly in `[-max, max]` (defaults 10 and 5 degrees), i.e. a hand-held camera
//!   held roughly level, as in the Stanford perspective images. Each view's orientation is a
//!   function of `(seed, panorama index, view index)` only, so the F195, F165, Pers and
//!   rectified sets of one seed look in exactly the same directions.
//! - **Sampling**: RGB is bilinear in the panorama, wrapping around the horizontal seam and
//!   across the poles ([`Panorama::wrap_index`]); depth and labels are nearest-neighbour (never
//!   blended across object edges). With `supersample = k > 1`, RGB averages `k x k` rays per
//!   pixel; depth, labels and mask always come from the pixel centre.
//! - **Validity**: a pixel is *inside the image* when the camera unprojects it and, for a
//!   fisheye, its ray makes an angle `theta <= fov / 2` with the optical axis (the image
//!   circle); outside it RGB is black, depth 0, label [`UNKNOWN_PNG_LABEL`]. The **mask** is
//!   inside the image and depth present (`> 0`).
//! - **Depth** stays the distance from the centre of projection along the ray (not z), as in
//!   the panoramas: re-projection does not change it.

use rayon::prelude::*;

use crate::camera::{Camera, CameraModel, Intrinsics, Pinhole};
use crate::data::panorama::geometry::V3;
use crate::data::panorama::Panorama;
use crate::data::rng::{tag, Rng};
use crate::data::UNKNOWN_PNG_LABEL;
use crate::error::{Error, Result};

/// A camera orientation in the panorama frame (see the module docs), radians.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Orientation {
    /// Turn about the vertical axis, + to the right.
    pub yaw: f64,
    /// Tilt, + up.
    pub pitch: f64,
    /// Turn about the optical axis, + clockwise seen from behind the camera.
    pub roll: f64,
}

impl Orientation {
    /// `R = R_y(yaw) R_x(pitch) R_z(roll)`, camera to world, row-major.
    pub fn matrix(&self) -> [[f64; 3]; 3] {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        let (sr, cr) = self.roll.sin_cos();
        let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
        let rx = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
        let rz = [[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]];
        matmul(&matmul(&ry, &rx), &rz)
    }

    /// The optical axis in the world: `(cos p sin y, -sin p, cos p cos y)`.
    pub fn forward(&self) -> V3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        [cp * sy, -sp, cp * cy]
    }
}

fn matmul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

fn apply(m: &[[f64; 3]; 3], v: V3) -> V3 {
    [0, 1, 2].map(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

/// How view orientations are drawn (see the module docs); angles in degrees as in config files.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewSampling {
    /// Pitch is uniform in `[-pitch_max_deg, pitch_max_deg]`.
    pub pitch_max_deg: f64,
    /// Roll is uniform in `[-roll_max_deg, roll_max_deg]`.
    pub roll_max_deg: f64,
}

impl Default for ViewSampling {
    fn default() -> Self {
        ViewSampling {
            pitch_max_deg: 10.0,
            roll_max_deg: 5.0,
        }
    }
}

impl ViewSampling {
    /// The orientation of view `view` of panorama `pano` in the data set seeded `seed`.
    pub fn orientation(&self, seed: u64, pano: u64, view: u64) -> Orientation {
        let mut rng = Rng::derive(seed, &[tag("view"), pano, view]);
        let yaw = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI);
        let p = self.pitch_max_deg.to_radians();
        let r = self.roll_max_deg.to_radians();
        Orientation {
            yaw,
            pitch: rng.uniform(-p, p),
            roll: rng.uniform(-r, r),
        }
    }
}

/// One view pixel: RGB, depth, label, mask.
type ViewPixel = ([u8; 3], f32, u8, bool);

/// An image rendered for a camera: row-major buffers of `height` rows of `width` pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// Width in pixels (the camera's).
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// 8-bit RGB; black outside the image.
    pub rgb: Vec<[u8; 3]>,
    /// Distance along the ray, metres; 0 = missing or outside the image.
    pub depth: Vec<f32>,
    /// Class ids in `CLASSES` order; [`UNKNOWN_PNG_LABEL`] for unknown or outside the image.
    pub labels: Vec<u8>,
    /// Inside the image and depth present.
    pub mask: Vec<bool>,
}

pub use crate::camera::max_ray_angle;

/// The angle of the rays that [`rectified_camera`] uses to measure a fisheye's focal length
/// at its principal point, radians: small enough that every model's distortion is negligible
/// (relative focal error ~1e-8 for the shipped lenses), large enough that the pixel offset
/// (~0.03 px at fx = 300) is far above round-off.
pub const PARAXIAL_ANGLE: f64 = 1e-4;

/// The unit camera ray of pixel `px` if it is inside the image (see the module docs).
pub fn pixel_ray(camera: &Camera, px: [f64; 2]) -> Option<V3> {
    let ray = camera.unproject(px)?;
    match max_ray_angle(camera) {
        Some(max) if ray[2].clamp(-1.0, 1.0).acos() > max => None,
        _ => Some(ray),
    }
}

/// Per pixel of `camera`, whether it is inside the image (row-major).
pub fn image_region(camera: &Camera) -> Vec<bool> {
    let [w, h] = camera.size();
    (0..w * h)
        .map(|i| pixel_ray(camera, [(i % w) as f64, (i / w) as f64]).is_some())
        .collect()
}

/// The rays of every pixel (and sub-pixel) of a camera, computed once and reused for every
/// view of a set (unprojecting a fisheye pixel takes a Newton solve).
#[derive(Clone, Debug)]
pub struct RayGrid {
    width: usize,
    height: usize,
    supersample: usize,
    /// Per pixel, the centre ray (row-major).
    centre: Vec<Option<V3>>,
    /// Per pixel, `k x k` sub-pixel rays (empty when `supersample == 1`).
    sub: Vec<Option<V3>>,
}

impl RayGrid {
    /// The rays of `camera` with `supersample x supersample` RGB rays per pixel at
    /// `(u + (j + 0.5) / k - 0.5, v + (i + 0.5) / k - 0.5)`.
    ///
    /// # Errors
    /// `supersample == 0`.
    pub fn new(camera: &Camera, supersample: usize) -> Result<Self> {
        if supersample == 0 {
            return Err(Error::InvalidArgument("supersample must be >= 1".into()));
        }
        let [w, h] = camera.size();
        let k = supersample;
        let centre: Vec<Option<V3>> = (0..w * h)
            .into_par_iter()
            .map(|i| pixel_ray(camera, [(i % w) as f64, (i / w) as f64]))
            .collect();
        let sub: Vec<Option<V3>> = if k == 1 {
            Vec::new()
        } else {
            (0..w * h * k * k)
                .into_par_iter()
                .map(|n| {
                    let (i, s) = (n / (k * k), n % (k * k));
                    let px = [
                        (i % w) as f64 + ((s % k) as f64 + 0.5) / k as f64 - 0.5,
                        (i / w) as f64 + ((s / k) as f64 + 0.5) / k as f64 - 0.5,
                    ];
                    pixel_ray(camera, px)
                })
                .collect()
        };
        Ok(RayGrid {
            width: w,
            height: h,
            supersample: k,
            centre,
            sub,
        })
    }

    /// Renders the view at `orientation` from `pano` (sampling rules in the module docs); rows
    /// in parallel.
    ///
    /// # Errors
    /// A panorama whose buffers do not match its size.
    pub fn render(&self, pano: &Panorama, orientation: &Orientation) -> Result<View> {
        pano.check()?;
        let (w, h, k) = (self.width, self.height, self.supersample);
        let rot = orientation.matrix();
        let rows: Vec<Vec<ViewPixel>> = (0..h)
            .into_par_iter()
            .map(|v| {
                (0..w)
                    .map(|u| {
                        let i = v * w + u;
                        let centre = self.centre[i];
                        let mut acc = [0.0f32; 3];
                        if k == 1 {
                            if let Some(ray) = centre {
                                acc = pano.bilinear_rgb(pano.pixel_of(apply(&rot, ray)));
                            }
                        } else {
                            for ray in self.sub[i * k * k..(i + 1) * k * k].iter().flatten() {
                                let c = pano.bilinear_rgb(pano.pixel_of(apply(&rot, *ray)));
                                for (a, c) in acc.iter_mut().zip(c) {
                                    *a += c;
                                }
                            }
                            acc = acc.map(|a| a / (k * k) as f32);
                        }
                        let rgb = acc.map(|a| a.round().clamp(0.0, 255.0) as u8);
                        match centre {
                            None => (rgb, 0.0, UNKNOWN_PNG_LABEL, false),
                            Some(ray) => {
                                let j = pano.nearest_index(pano.pixel_of(apply(&rot, ray)));
                                let d = pano.depth[j];
                                (rgb, d, pano.labels[j], d > 0.0)
                            }
                        }
                    })
                    .collect()
            })
            .collect();
        Ok(collect_view(w, h, rows))
    }
}

/// Renders the view of `camera` at `orientation` from `pano` (sampling rules in the module
/// docs). For many views of one camera, build a [`RayGrid`] once instead.
///
/// # Errors
/// `supersample == 0`, or a panorama whose buffers do not match its size.
pub fn render_view(
    pano: &Panorama,
    camera: &Camera,
    orientation: &Orientation,
    supersample: usize,
) -> Result<View> {
    RayGrid::new(camera, supersample)?.render(pano, orientation)
}

fn collect_view(w: usize, h: usize, rows: Vec<Vec<ViewPixel>>) -> View {
    let (rgb, depth, labels, mask) = rows.into_iter().flatten().collect();
    View {
        width: w,
        height: h,
        rgb,
        depth,
        labels,
        mask,
    }
}

/// The pinhole camera a fisheye is rectified to: the same image size, the fisheye's principal
/// point `c = project(0, 0, 1)`, and its focal lengths at the principal point,
/// `f_x = (project(sin e, 0, cos e) - c)_u / e` (likewise `f_y`) with `e` =
/// [`PARAXIAL_ANGLE`] (for Kannala-Brandt that is `fx`, as `d'(0) = 1`: OpenCV's
/// `fisheye::undistortImage` with `Knew = K`). With `hfov_deg`, `f_x = (W / 2) /
/// tan(hfov / 2)` instead and `f_y` keeps the fisheye's aspect.
///
/// # Errors
/// The camera is not a fisheye model, or its field of view is 180 degrees or more (a pinhole
/// image cannot hold rays at 90 degrees or beyond, so such a fisheye cannot be rectified);
/// `hfov_deg` outside `(0, 180)`.
pub fn rectified_camera(fisheye: &Camera, hfov_deg: Option<f64>) -> Result<Camera> {
    let Some(half) = max_ray_angle(fisheye) else {
        return Err(Error::InvalidArgument(format!(
            "rectification needs a fisheye camera (with an image circle), not a {} camera",
            fisheye.model_name()
        )));
    };
    let fov_deg = 2.0 * half.to_degrees();
    if fov_deg >= 180.0 {
        return Err(Error::InvalidArgument(format!(
            "cannot rectify a {fov_deg} deg fisheye: a perspective image holds only rays below \
             90 deg (FOV < 180)"
        )));
    }
    let e = PARAXIAL_ANGLE;
    let paraxial = || -> Option<([f64; 2], f64, f64)> {
        let c = fisheye.project([0.0, 0.0, 1.0])?;
        let px = fisheye.project([e.sin(), 0.0, e.cos()])?;
        let py = fisheye.project([0.0, e.sin(), e.cos()])?;
        Some((c, (px[0] - c[0]) / e, (py[1] - c[1]) / e))
    };
    let Some((c, fx, fy)) = paraxial().filter(|(_, fx, fy)| *fx > 0.0 && *fy > 0.0) else {
        return Err(Error::InvalidArgument(format!(
            "the {} camera does not project its optical axis to a principal point",
            fisheye.model_name()
        )));
    };
    let [width, height] = fisheye.size();
    let (f, aspect) = match hfov_deg {
        None => (fx, fy / fx),
        Some(h) if h > 0.0 && h < 180.0 => {
            (width as f64 / 2.0 / (h.to_radians() / 2.0).tan(), fy / fx)
        }
        Some(h) => {
            return Err(Error::InvalidArgument(format!(
                "rectified horizontal FOV must be in (0, 180) deg, found {h}"
            )))
        }
    };
    let intrinsics = Intrinsics::from_parts([f, f * aspect, c[0], c[1]], [width, height]);
    Ok(Camera::Pinhole(Pinhole::new(intrinsics)?))
}

/// The fisheye pixel each pinhole pixel samples when rectifying, computed once per camera
/// pair (see [`rectify`]).
#[derive(Clone, Debug)]
pub struct Rectifier {
    fisheye_size: [usize; 2],
    size: [usize; 2],
    /// Per pinhole pixel, the fisheye pixel coordinates, or `None` outside the image circle.
    source: Vec<Option<[f64; 2]>>,
}

impl Rectifier {
    /// The mapping from `pinhole` pixels to `fisheye` pixels.
    ///
    /// # Errors
    /// `fisheye` is not a fisheye with FOV < 180 deg, or `pinhole` is not a pinhole.
    pub fn new(fisheye: &Camera, pinhole: &Camera) -> Result<Self> {
        rectified_camera(fisheye, None)?; // the same checks on the fisheye
        if !matches!(pinhole, Camera::Pinhole(_)) {
            return Err(Error::InvalidArgument(
                "rectification target must be a pinhole camera".into(),
            ));
        }
        let max = max_ray_angle(fisheye).expect("fisheye");
        let [w, h] = pinhole.size();
        let source = (0..w * h)
            .into_par_iter()
            .map(|i| {
                let ray = pinhole.unproject([(i % w) as f64, (i / w) as f64])?;
                if ray[2].clamp(-1.0, 1.0).acos() > max {
                    return None;
                }
                fisheye.project(ray)
            })
            .collect();
        Ok(Rectifier {
            fisheye_size: fisheye.size(),
            size: [w, h],
            source,
        })
    }

    /// Re-projects a fisheye view (see [`rectify`]).
    ///
    /// # Errors
    /// The view does not have the fisheye's size.
    pub fn apply(&self, view: &View) -> Result<View> {
        let [fw, fh] = self.fisheye_size;
        if [view.width, view.height] != [fw, fh] {
            return Err(Error::InvalidArgument(format!(
                "view is {}x{}, the fisheye camera {}x{}",
                view.width, view.height, fw, fh
            )));
        }
        let [w, h] = self.size;
        let rows: Vec<Vec<ViewPixel>> = (0..h)
            .into_par_iter()
            .map(|v| {
                (0..w)
                    .map(|u| {
                        let outside = ([0u8; 3], 0.0, UNKNOWN_PNG_LABEL, false);
                        let Some(px) = self.source[v * w + u] else {
                            return outside;
                        };
                        let (nu, nv) = (px[0].round(), px[1].round());
                        if nu < 0.0 || nv < 0.0 || nu >= fw as f64 || nv >= fh as f64 {
                            return outside;
                        }
                        let ni = nv as usize * fw + nu as usize;
                        let rgb = bilinear_clamped(&view.rgb, fw, fh, px);
                        (rgb, view.depth[ni], view.labels[ni], view.mask[ni])
                    })
                    .collect()
            })
            .collect();
        Ok(collect_view(w, h, rows))
    }
}

/// Re-projects a fisheye `view` (rendered with `fisheye`) to `pinhole`: each pinhole pixel's
/// ray is projected into the fisheye image; RGB is bilinear there (clamped at the border),
/// depth, label and mask nearest. Pinhole pixels whose ray leaves the fisheye's image circle
/// are outside the image (black, depth 0, unknown, mask false). For many views of one camera
/// pair, build a [`Rectifier`] once instead.
///
/// # Errors
/// `fisheye` is not a fisheye with FOV < 180 deg, `pinhole` is not a pinhole, or the view does
/// not have the fisheye's size.
pub fn rectify(view: &View, fisheye: &Camera, pinhole: &Camera) -> Result<View> {
    Rectifier::new(fisheye, pinhole)?.apply(view)
}

/// Bilinear RGB with coordinates clamped to the image.
fn bilinear_clamped(rgb: &[[u8; 3]], w: usize, h: usize, px: [f64; 2]) -> [u8; 3] {
    let x = px[0].clamp(0.0, (w - 1) as f64);
    let y = px[1].clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (wx, wy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let p = |xx: usize, yy: usize| rgb[yy * w + xx];
    [0, 1, 2].map(|k| {
        let a = p(x0, y0)[k] as f32 * (1.0 - wx) + p(x1, y0)[k] as f32 * wx;
        let b = p(x0, y1)[k] as f32 * (1.0 - wx) + p(x1, y1)[k] as f32 * wx;
        (a * (1.0 - wy) + b * wy).round().clamp(0.0, 255.0) as u8
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{KannalaBrandt, PixelConvention};
    use crate::data::panorama::render_procedural;

    fn shipped(name: &str) -> Camera {
        crate::camera::load(format!(
            "{}/data/cameras/{name}",
            env!("CARGO_MANIFEST_DIR")
        ))
        .unwrap()
    }

    /// A panorama whose depth is `1 + pixel index` (every pixel distinguishable by nearest
    /// sampling) and whose RGB is a smooth function of the direction.
    fn indexed_pano(height: usize) -> Panorama {
        let width = 2 * height;
        let n = width * height;
        Panorama {
            width,
            height,
            rgb: (0..n)
                .map(|i| {
                    let d =
                        Panorama::direction(width, height, (i % width) as f64, (i / width) as f64);
                    d.map(|c| ((c + 1.0) * 127.0) as u8)
                })
                .collect(),
            depth: (0..n).map(|i| 1.0 + i as f32).collect(),
            labels: (0..n).map(|i| (i % 13) as u8).collect(),
        }
    }

    #[test]
    fn orientation_matrix_is_a_rotation_with_the_documented_axes() {
        let o = Orientation {
            yaw: 0.7,
            pitch: -0.2,
            roll: 0.3,
        };
        let m = o.matrix();
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        let f = apply(&m, [0.0, 0.0, 1.0]);
        let g = o.forward();
        assert!((0..3).all(|k| (f[k] - g[k]).abs() < 1e-12));
        // Yaw + turns right, pitch + looks up.
        let right = Orientation {
            yaw: std::f64::consts::FRAC_PI_2,
            ..Default::default()
        };
        assert!((right.forward()[0] - 1.0).abs() < 1e-12);
        let up = Orientation {
            pitch: 0.5,
            ..Default::default()
        };
        assert!(up.forward()[1] < 0.0);
    }

    #[test]
    fn principal_point_looks_along_the_forward_direction() {
        // A small F195-like camera with an integer principal point.
        let intrinsics = Intrinsics::from_parts([30.0, 30.0, 32.0, 28.0], [65, 57]);
        let k = [0.0, -3.5e-5, 1e-7, -6.9e-11];
        let cam = Camera::KannalaBrandt(KannalaBrandt::new(intrinsics, k, 195.0).unwrap());
        let pano = indexed_pano(64);
        let sampling = ViewSampling::default();
        for k in 0..6 {
            let o = sampling.orientation(3, 0, k);
            let view = render_view(&pano, &cam, &o, 1).unwrap();
            let i = 28 * 65 + 32;
            let expect = pano.depth[pano.nearest_index(pano.pixel_of(o.forward()))];
            assert_eq!(view.depth[i], expect, "view {k}");
            assert!(view.mask[i]);
        }
    }

    #[test]
    fn mask_is_false_exactly_outside_the_image_circle() {
        let cam = shipped("f195.toml").rescaled([0.1, 0.1], PixelConvention::HalfPixel);
        let (_, pano) = render_procedural(4, 0, 64);
        let view = render_view(&pano, &cam, &Orientation::default(), 1).unwrap();
        let [w, h] = cam.size();
        let half_fov = 97.5f64.to_radians();
        let (mut inside, mut outside) = (0, 0);
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                let ray = cam.unproject([u as f64, v as f64]).unwrap();
                let theta = ray[2].acos();
                if theta > half_fov {
                    assert!(!view.mask[i] && view.rgb[i] == [0; 3] && view.depth[i] == 0.0);
                    assert_eq!(view.labels[i], UNKNOWN_PNG_LABEL);
                    outside += 1;
                } else {
                    assert!(view.mask[i], "({u}, {v}) theta {theta}");
                    inside += 1;
                }
            }
        }
        // The 195 degree circle leaves the four corners of the image dark.
        assert!(outside > 0 && inside > outside, "{inside} {outside}");
        // The image region helper agrees.
        let region = image_region(&cam);
        assert_eq!(region.iter().filter(|&&b| b).count(), inside);
    }

    #[test]
    fn looking_at_the_seam_equals_looking_at_a_rolled_panorama() {
        // Yaw pi looks at the seam of `pano`; yaw 0 looks at the same content in `rolled`
        // (columns turned by half the width), where it sits in the middle of the image. With
        // correct wrapping the two views are the same.
        let (_, pano) = render_procedural(6, 1, 64);
        let (w, h) = (pano.width, pano.height);
        let roll = |i: usize| (i / w) * w + (i % w + w / 2) % w;
        let rolled = Panorama {
            rgb: (0..w * h).map(|i| pano.rgb[roll(i)]).collect(),
            depth: (0..w * h).map(|i| pano.depth[roll(i)]).collect(),
            labels: (0..w * h).map(|i| pano.labels[roll(i)]).collect(),
            ..pano.clone()
        };
        let cam = shipped("f195.toml").rescaled([0.06, 0.06], PixelConvention::HalfPixel);
        let at_seam = Orientation {
            yaw: std::f64::consts::PI,
            pitch: 0.3,
            ..Default::default()
        };
        let a = render_view(&pano, &cam, &at_seam, 2).unwrap();
        let b = render_view(
            &rolled,
            &cam,
            &Orientation {
                yaw: 0.0,
                ..at_seam
            },
            2,
        )
        .unwrap();
        let n = a.rgb.len();
        for i in 0..n {
            for k in 0..3 {
                // Rounding of lon +- pi may move a bilinear weight by ~1e-13: one level at most.
                assert!(
                    (a.rgb[i][k] as i32 - b.rgb[i][k] as i32).abs() <= 1,
                    "pixel {i}"
                );
            }
        }
        let same = (0..n).filter(|&i| a.labels[i] == b.labels[i]).count();
        assert!(same as f64 > 0.99 * n as f64, "{same} / {n}");
        // Bilinear sampling between the last and the first column mixes the two.
        let px = pano.bilinear_rgb([-0.5, 10.0]);
        let (l, r) = (pano.rgb[10 * w + w - 1], pano.rgb[10 * w]);
        for k in 0..3 {
            assert!((px[k] - (l[k] as f32 + r[k] as f32) / 2.0).abs() < 1e-3);
        }
    }

    #[test]
    fn rectified_f165_matches_a_direct_pinhole_rendering() {
        let fish = shipped("f165.toml").rescaled([0.15, 0.15], PixelConvention::HalfPixel);
        let pin = rectified_camera(&fish, None).unwrap();
        let (_, pano) = render_procedural(8, 2, 128);
        let o = ViewSampling::default().orientation(8, 2, 0);
        let fview = render_view(&pano, &fish, &o, 1).unwrap();
        let rect = rectify(&fview, &fish, &pin).unwrap();
        let direct = render_view(&pano, &pin, &o, 1).unwrap();
        let n = rect.labels.len();
        let agree = (0..n)
            .filter(|&i| rect.labels[i] == direct.labels[i])
            .count();
        // Two nearest-neighbour resamplings move object edges by up to a pixel: >= 95 % agree.
        assert!(agree as f64 > 0.95 * n as f64, "{agree} / {n}");
        let mad: f64 = (0..n)
            .map(|i| {
                (0..3)
                    .map(|k| (rect.rgb[i][k] as f64 - direct.rgb[i][k] as f64).abs())
                    .sum::<f64>()
                    / 3.0
            })
            .sum::<f64>()
            / n as f64;
        // Bilinear twice blurs edges a little; a wrong geometry would differ by tens of levels.
        assert!(mad < 10.0, "{mad}");
        // Geometric round trip: pinhole pixel -> fisheye pixel -> ray -> pinhole pixel.
        for (u, v) in [(0.0, 0.0), (80.0, 70.0), (161.0, 143.0)] {
            let ray = pin.unproject([u, v]).unwrap();
            let fpx = fish.project(ray).unwrap();
            let back = pin.project(fish.unproject(fpx).unwrap()).unwrap();
            assert!((back[0] - u).abs() < 1e-9 && (back[1] - v).abs() < 1e-9);
        }
    }

    #[test]
    fn rectifying_a_fisheye_of_180_degrees_or_more_is_an_error() {
        let msg = rectified_camera(&shipped("f195.toml"), None)
            .unwrap_err()
            .to_string();
        assert!(msg.contains("195") && msg.contains("180"), "{msg}");
        assert!(rectified_camera(&shipped("pers.toml"), None).is_err());
        let f165 = shipped("f165.toml");
        let Camera::Pinhole(p) = rectified_camera(&f165, Some(90.0)).unwrap() else {
            panic!()
        };
        assert!((p.fx - 540.0).abs() < 1e-9);
        assert!(rectified_camera(&f165, Some(180.0)).is_err());
    }

    #[test]
    fn every_shipped_camera_renders_with_its_image_region() {
        // Every model in data/cameras: the mask is false exactly outside the image (the image
        // circle of a fisheye model), and fisheyes below 180 deg rectify to a pinhole that sees
        // the same principal ray.
        let (_, pano) = render_procedural(9, 0, 64);
        let dir = format!("{}/data/cameras", env!("CARGO_MANIFEST_DIR"));
        let mut names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".toml"))
            .collect();
        names.sort();
        assert!(names.len() >= 3, "{names:?}");
        let mut rectified = 0;
        for name in names {
            let cam = shipped(&name);
            let s = 40.0 / cam.size()[0] as f64;
            let cam = cam.rescaled([s, s], PixelConvention::HalfPixel);
            let o = ViewSampling::default().orientation(9, 0, 1);
            let view = render_view(&pano, &cam, &o, 1).unwrap();
            let region = image_region(&cam);
            assert_eq!(view.mask, region, "{name}");
            assert!(region.iter().any(|&r| r), "{name}");
            match max_ray_angle(&cam) {
                Some(half) if half.to_degrees() < 90.0 => {
                    let pin = rectified_camera(&cam, None).unwrap();
                    let c = cam.project([0.0, 0.0, 1.0]).unwrap();
                    assert_eq!(pin.project([0.0, 0.0, 1.0]), Some(c), "{name}");
                    rectified += 1;
                }
                Some(_) => assert!(rectified_camera(&cam, None).is_err(), "{name}"),
                None => assert!(rectified_camera(&cam, None).is_err(), "{name}"),
            }
        }
        // At least F165 and the double sphere example.
        assert!(rectified >= 2, "{rectified}");
        // For Kannala-Brandt the paraxial focal is fx (d'(0) = 1, k1 ~ 0 for F165).
        let f165 = shipped("f165.toml");
        let Camera::Pinhole(p) = rectified_camera(&f165, None).unwrap() else {
            panic!()
        };
        assert!(
            (p.fx - 326.0).abs() < 1e-6 && (p.cx - 540.0).abs() < 1e-9,
            "{p:?}"
        );
    }

    #[test]
    fn views_are_deterministic_and_orientations_differ() {
        let s = ViewSampling::default();
        assert_eq!(s.orientation(1, 2, 3), s.orientation(1, 2, 3));
        assert_ne!(s.orientation(1, 2, 3), s.orientation(1, 2, 4));
        let o = s.orientation(1, 2, 3);
        assert!(o.pitch.abs() <= 10f64.to_radians() && o.roll.abs() <= 5f64.to_radians());
    }
}
