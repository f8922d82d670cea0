//! The paper's "fisheye calibrated kernel" (Section 3.2): fixed deformable-conv offsets from a
//! camera calibration.
//!
//! For an anchor pixel `(u0, v0)` (the kernel centre of an output pixel), a virtual perspective
//! kernel with taps `p_ij = (j dil_x, i dil_y, d)` (i, j centred on 0) and focal
//!
//! ```text
//! d = k / (2 tan(alpha / 2)),   alpha = k * FOV / W_fm
//! ```
//!
//! (k = kernel width, W_fm = feature-map width) is rotated by the minimal rotation taking the
//! optical axis onto the anchor's back-projected ray (or, for cameras that ask for
//! [`KernelFrame::Upright`], by yaw and pitch without roll), and each tap is projected with the
//! camera scaled to the feature map. Offsets are the projected taps minus the regular grid.
//!
//! Conventions:
//! - Resolution scaling: the network input is the camera image padded by `(p_w, p_h)` pixels on
//!   the right / bottom; intrinsics scale by `s = W_fm / (W_c + p_w)` (and likewise in height);
//!   the principal point moves by a [`PixelConvention`] (`half-pixel` by default, `paper` for the
//!   authors' released code).
//! - Anchors follow torchvision: output pixel `(oy, ox)` samples tap `(i, j)` at
//!   `(oy*stride - pad + i*dil, ox*stride - pad + j*dil)` plus the offset; the anchor is the
//!   centre tap. Stride > 1 works (the authors' code is wrong there).
//! - Layout is torchvision's: `[2*kh*kw, H_out, W_out]`, per tap (row-major i, j) the pair
//!   `(dy, dx)`.
//! - Outside the model: an anchor the camera cannot unproject gets zero offsets (a standard
//!   kernel; on a fisheye such pixels lie outside the image circle and are black anyway), and a
//!   tap the camera cannot project keeps its regular position. Both are counted in
//!   [`Offsets::fallback_anchors`] / [`Offsets::fallback_taps`].
//! - Panoramas ([`CameraModel::wraps_horizontally`]): a tap's `dx` is taken modulo the
//!   feature-map width `W` to the representative nearest the regular tap,
//!   `dx - W round(dx / W)`, so that a kernel continuing across the seam gets small offsets (the
//!   sampling plan wraps columns, `calibconv::ops::Border::WrapX`). Such a camera cannot be padded
//!   horizontally (`p_w = 0`): the image must span exactly 360 degrees.

mod maps;

pub use maps::{ray_maps, RayMaps, RAY_MAPS};

use rayon::prelude::*;

use crate::camera::{Camera, CameraModel, KernelFrame, PixelConvention};
use crate::error::{Error, Result};
use crate::vec3::{cross, Mat3};

/// Geometry of one convolution layer: all pairs are `[y, x]` (rows, columns).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LayerGeometry {
    /// Kernel size `[kh, kw]`, both odd.
    pub kernel: [usize; 2],
    pub stride: [usize; 2],
    /// Zero padding of the convolution itself.
    pub padding: [usize; 2],
    pub dilation: [usize; 2],
}

impl LayerGeometry {
    /// A `k x k` kernel, stride 1, dilation 1, "same" padding `(k - 1) / 2`.
    pub fn same(k: usize) -> Self {
        LayerGeometry {
            kernel: [k, k],
            stride: [1, 1],
            padding: [(k - 1) / 2, (k - 1) / 2],
            dilation: [1, 1],
        }
    }

    /// Output size `[H_out, W_out]` for an input feature map `[H, W]` (PyTorch's formula), or
    /// `None` if the kernel does not fit (or the sizes overflow `usize`).
    pub fn output_size(&self, input: [usize; 2]) -> Option<[usize; 2]> {
        let mut out = [0; 2];
        for a in 0..2 {
            let span = self.dilation[a]
                .checked_mul(self.kernel[a].checked_sub(1)?)?
                .checked_add(1)?;
            let padded = input[a].checked_add(self.padding[a].checked_mul(2)?)?;
            if padded < span || self.stride[a] == 0 {
                return None;
            }
            out[a] = (padded - span) / self.stride[a] + 1;
        }
        Some(out)
    }

    fn check(&self) -> Result<()> {
        let ok = self.kernel.iter().all(|&k| k % 2 == 1)
            && self.stride.iter().all(|&s| s >= 1)
            && self.dilation.iter().all(|&d| d >= 1);
        if ok {
            Ok(())
        } else {
            Err(Error::InvalidArgument(format!(
                "layer geometry {self:?}: kernel sizes must be odd, stride and dilation >= 1"
            )))
        }
    }
}

/// How the network input relates to the camera image, and which pixel convention to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct InputFrame {
    /// Padding `[p_w, p_h]` added to the right and bottom of the camera image.
    pub padding: [usize; 2],
    pub convention: PixelConvention,
}

/// Offsets of one layer, in torchvision's layout `[2*kh*kw, H_out, W_out]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Offsets {
    /// Row-major `[2*kh*kw, H_out, W_out]`, pairs `(dy, dx)` per tap.
    pub data: Vec<f32>,
    pub kernel: [usize; 2],
    /// Input feature-map size `[H, W]`.
    pub input_size: [usize; 2],
    /// Output size `[H_out, W_out]`.
    pub output_size: [usize; 2],
    /// Anchors the camera could not unproject (given zero offsets).
    pub fallback_anchors: usize,
    /// Taps the camera could not project (left at their regular position).
    pub fallback_taps: usize,
}

impl Offsets {
    /// `(dy, dx)` of tap `(i, j)` at output pixel `(oy, ox)`.
    pub fn get(&self, tap: [usize; 2], out: [usize; 2]) -> [f32; 2] {
        let k = tap[0] * self.kernel[1] + tap[1];
        let plane = self.output_size[0] * self.output_size[1];
        let p = out[0] * self.output_size[1] + out[1];
        [
            self.data[2 * k * plane + p],
            self.data[(2 * k + 1) * plane + p],
        ]
    }

    /// The shape of [`Offsets::data`]: `[2*kh*kw, H_out, W_out]`.
    pub fn shape(&self) -> [usize; 3] {
        let [ho, wo] = self.output_size;
        [2 * self.kernel[0] * self.kernel[1], ho, wo]
    }

    /// Largest offset magnitude (pixels).
    pub fn max_abs(&self) -> f32 {
        self.data.iter().fold(0.0f32, |m, v| m.max(v.abs()))
    }
}

/// Rotation matrix (row-major) of the minimal rotation taking `(0, 0, 1)` onto the unit ray `r`
/// (Rodrigues' formula about `z x r`; a half turn about x for `r = -z`). Without branches, so
/// that a loop over anchors vectorises.
#[inline(always)]
pub fn align_optical_axis(r: [f64; 3]) -> Mat3 {
    let (s, c) = ((r[0] * r[0] + r[1] * r[1]).sqrt(), r[2]);
    // Unit axis k = (z x r) / |z x r| = (-ry, rx, 0) / s.
    let (kx, ky) = (-r[1] / s, r[0] / s);
    let t = 1.0 - c;
    // R = c I + s [k]x + t k k^T with kz = 0.
    let rodrigues = [
        [c + t * kx * kx, t * kx * ky, s * ky],
        [t * kx * ky, c + t * ky * ky, -s * kx],
        [-s * ky, s * kx, c],
    ];
    // On the axis (no rotation axis): the identity forward, a half turn about x backward.
    let d = if c > 0.0 { 1.0 } else { -1.0 };
    let on_axis = [[1.0, 0.0, 0.0], [0.0, d, 0.0], [0.0, 0.0, d]];
    let axis = s < 1e-12;
    std::array::from_fn(|i| {
        std::array::from_fn(|j| if axis { on_axis[i][j] } else { rodrigues[i][j] })
    })
}

/// Rotation matrix (row-major) taking `(0, 0, 1)` onto the unit ray `r` with no roll: its
/// columns are `e = (r_z, 0, -r_x) / |(r_x, r_z)|` (the direction of increasing longitude
/// `atan2(r_x, r_z)`), `r x e` (towards decreasing latitude, "down") and `r`. At the poles
/// (`r_x = r_z = 0`) `e = (1, 0, 0)`.
pub fn upright_frame(r: [f64; 3]) -> Mat3 {
    let q = r[0].hypot(r[2]);
    let e = if q > 0.0 {
        [r[2] / q, 0.0, -r[0] / q]
    } else {
        [1.0, 0.0, 0.0]
    };
    let d = cross(r, e);
    [[e[0], d[0], r[0]], [e[1], d[1], r[1]], [e[2], d[2], r[2]]]
}

/// Focal length `d` (pixels) of the virtual perspective kernel of width `k` on a feature map of
/// width `w_fm` for a camera of field of view `fov` (radians): `d = k / (2 tan(alpha / 2))` with
/// `alpha = k * fov / w_fm`.
pub fn kernel_focal(k: usize, fov: f64, w_fm: usize) -> Result<f64> {
    let alpha = k as f64 * fov / w_fm as f64;
    // The virtual kernel must see less than a half space to be a perspective patch.
    if !(alpha > 0.0 && alpha < std::f64::consts::PI * 0.99) {
        return Err(Error::InvalidArgument(format!(
            "a {k}-wide kernel on a {w_fm}-pixel-wide feature map spans {:.1} deg of a {:.1} deg \
             field of view; calibrated kernels need it under 178 deg (use a wider feature map)",
            alpha.to_degrees(),
            fov.to_degrees()
        )));
    }
    Ok(k as f64 / (2.0 * (alpha / 2.0).tan()))
}

/// The most values (float32, `2 * kh * kw * H_out * W_out`) one layer's offsets may hold:
/// `2^31 - 1`, 8 GiB, already twice what a sampling plan can index with its int32 indices. A
/// larger request is refused before anything is allocated.
pub const MAX_OFFSET_VALUES: usize = i32::MAX as usize;

/// The zeroed buffer of `2 * taps * H_out * W_out` offsets for a `input_size` input, or an error
/// naming the size if it is over [`MAX_OFFSET_VALUES`] or cannot be allocated (checked before
/// allocating: no abort).
fn offsets_buffer(
    input_size: [usize; 2],
    kernel: [usize; 2],
    output: [usize; 2],
) -> Result<Vec<f32>> {
    let [kh, kw] = kernel;
    let [ho, wo] = output;
    let too_large = |why: &str| {
        let bytes = 2.0 * kh as f64 * kw as f64 * ho as f64 * wo as f64 * 4.0;
        Error::InvalidArgument(format!(
            "a {}x{} input is too large: the offsets of a {kh}x{kw} kernel on it, \
             2 x {kh}x{kw} x {ho}x{wo} float32 ({:.1} GB), {why}",
            input_size[0],
            input_size[1],
            bytes / 1e9,
        ))
    };
    let values = [2, kh, kw, ho, wo]
        .into_iter()
        .try_fold(1usize, usize::checked_mul)
        .filter(|&n| n <= MAX_OFFSET_VALUES)
        .ok_or_else(|| {
            too_large(&format!(
                "exceed the limit of {MAX_OFFSET_VALUES} values ({:.1} GB)",
                MAX_OFFSET_VALUES as f64 * 4.0 / 1e9
            ))
        })?;
    zeroed(values).ok_or_else(|| too_large("cannot be allocated"))
}

/// `n` zeros, or `None` if they cannot be allocated. Zeroed memory from the allocator (fresh
/// pages for large sizes) rather than a fill: the pages are first touched by the parallel row
/// tasks that write them, not by one thread up front.
fn zeroed(n: usize) -> Option<Vec<f32>> {
    if n == 0 {
        return Some(Vec::new());
    }
    let layout = std::alloc::Layout::array::<f32>(n).ok()?;
    // SAFETY: `layout` has a non-zero size (n > 0).
    let ptr = unsafe { std::alloc::alloc_zeroed(layout) }.cast::<f32>();
    if ptr.is_null() {
        return None;
    }
    // SAFETY: `ptr` comes from the global allocator with the layout of `n` f32 (what a Vec of
    // capacity `n` uses), and all-zero bytes are `n` valid values (0.0).
    let mut v = unsafe { Vec::from_raw_parts(ptr, n, n) };
    crate::memory::advise_huge_pages(&mut v);
    Some(v)
}

/// Computes the calibrated offsets of one layer.
///
/// `input_size` is the layer's input feature map `[H, W]`; the camera is scaled from its image
/// (plus `frame.padding`) to that size. Runs in parallel over output rows; the result does not
/// depend on the number of threads.
///
/// # Errors
/// An invalid geometry, a kernel that does not fit or spans too wide a field of view, a
/// padded panorama, and sizes whose offsets would exceed [`MAX_OFFSET_VALUES`] or cannot be
/// allocated (an error naming the size, before allocating).
pub fn compute_offsets(
    camera: &Camera,
    input_size: [usize; 2],
    geometry: &LayerGeometry,
    frame: &InputFrame,
) -> Result<Offsets> {
    geometry.check()?;
    let output_size = geometry.output_size(input_size).ok_or_else(|| {
        Error::InvalidArgument(format!(
            "kernel {:?} does not fit a {}x{} feature map",
            geometry, input_size[0], input_size[1]
        ))
    })?;
    let [w_c, h_c] = camera.size();
    let wrap = camera.wraps_horizontally();
    if wrap && frame.padding[0] != 0 {
        return Err(Error::InvalidArgument(format!(
            "a panorama wraps across its left/right edge, so it cannot be padded horizontally \
             (padding {:?}: use p_w = 0)",
            frame.padding
        )));
    }
    let period = input_size[1] as f64;
    let frame_kind = camera.kernel_frame();
    let scale = [
        input_size[1] as f64 / (w_c + frame.padding[0]) as f64,
        input_size[0] as f64 / (h_c + frame.padding[1]) as f64,
    ];
    let cam = camera.rescaled(scale, frame.convention);
    let [kh, kw] = geometry.kernel;
    let d = kernel_focal(kw, camera.fov(), input_size[1])?;
    let [ho, wo] = output_size;
    let mut data = offsets_buffer(input_size, geometry.kernel, output_size)?;
    let (ch, cw) = ((kh - 1) / 2, (kw - 1) / 2);
    let taps = kh * kw;

    // The planes [2 * taps, H_out, W_out] cut into rows, grouped by output row: every row task
    // writes its (dy, dx) straight into its 2 * taps row slices (untouched taps stay 0).
    let mut by_row: Vec<Vec<&mut [f32]>> = (0..ho).map(|_| Vec::with_capacity(2 * taps)).collect();
    for (i, chunk) in data.chunks_mut(wo.max(1)).enumerate() {
        by_row[i % ho].push(chunk); // chunk i is plane i / ho, row i % ho
    }
    // Anchor columns (the same in every row), then per row: each anchor's rotation, kept as 9
    // columns of entries, and per tap the row's rays as columns `x, y, z`, projected together
    // (`CameraModel::project_columns`: vectorised for Kannala-Brandt).
    let anchor_x: Vec<f64> = (0..wo)
        .map(|ox| {
            (ox * geometry.stride[1] + cw * geometry.dilation[1]) as f64
                - geometry.padding[1] as f64
        })
        .collect();
    let counts: Vec<(usize, usize)> = by_row
        .into_par_iter()
        .enumerate()
        .map(|(oy, mut out)| {
            let ay = (oy * geometry.stride[0] + ch * geometry.dilation[0]) as f64
                - geometry.padding[0] as f64;
            let mut rot = vec![0.0; 9 * wo];
            let mut anchored = vec![false; wo];
            let mut anchor_ray = [vec![0.0; wo], vec![0.0; wo], vec![0.0; wo]];
            {
                let [x, y, z] = &mut anchor_ray;
                let row = vec![ay; wo];
                cam.unproject_columns([&anchor_x, &row], [x, y, z], &mut anchored);
            }
            let bad_anchors = anchored.iter().filter(|&&a| !a).count();
            let [x, y, z] = &anchor_ray;
            let (x, y, z) = (&x[..wo], &y[..wo], &z[..wo]);
            let mut entries: Vec<&mut [f64]> = rot.chunks_exact_mut(wo.max(1)).collect();
            for ox in 0..wo {
                let ray = [x[ox], y[ox], z[ox]];
                // (Anchors without a ray get some rotation; their taps are dropped below.)
                let m = match frame_kind {
                    KernelFrame::MinimalRotation => align_optical_axis(ray),
                    KernelFrame::Upright => upright_frame(ray),
                };
                for (e, &entry) in m.as_flattened().iter().enumerate() {
                    entries[e][ox] = entry;
                }
            }
            let col = |e: usize| &rot[e * wo..(e + 1) * wo];
            let mut ray = [vec![0.0; wo], vec![0.0; wo], vec![0.0; wo]];
            let (mut u, mut v, mut ok) = (vec![0.0; wo], vec![0.0; wo], vec![false; wo]);
            let mut bad_taps = 0;
            for i in 0..kh {
                let ty = (i as f64 - ch as f64) * geometry.dilation[0] as f64;
                for j in 0..kw {
                    let tx = (j as f64 - cw as f64) * geometry.dilation[1] as f64;
                    // The tap rotated onto each anchor's ray: row r of the matrix times
                    // (tx, ty, d), as `vec3::rotate`.
                    for (r, out) in ray.iter_mut().enumerate() {
                        let (m0, m1, m2) = (col(3 * r), col(3 * r + 1), col(3 * r + 2));
                        for ox in 0..wo {
                            out[ox] = m0[ox] * tx + m1[ox] * ty + m2[ox] * d;
                        }
                    }
                    cam.project_columns([&ray[0], &ray[1], &ray[2]], &mut u, &mut v, &mut ok);
                    // An anchor without a ray, and a tap without a pixel, get zero offsets (the
                    // tap's regular position).
                    let k = i * kw + j;
                    let [dy_row, dx_row] =
                        out.get_disjoint_mut([2 * k, 2 * k + 1]).expect("2 rows");
                    // All of length `wo`, so that the loops below vectorise without bounds checks.
                    let (dy_row, dx_row) = (&mut dy_row[..wo], &mut dx_row[..wo]);
                    let (u, v, ok, anchored) = (&u[..wo], &v[..wo], &ok[..wo], &anchored[..wo]);
                    let anchor_x = &anchor_x[..wo];
                    bad_taps += anchored.iter().zip(ok).filter(|&(&a, &o)| a & !o).count();
                    // Zero unless kept, as a bit mask: the loop has no branch and vectorises.
                    let kept = |ox: usize, value: f64| {
                        let mask = 0u32.wrapping_sub(u32::from(anchored[ox] & ok[ox]));
                        f32::from_bits((value as f32).to_bits() & mask)
                    };
                    for ox in 0..wo {
                        dy_row[ox] = kept(ox, v[ox] - (ay + ty));
                        dx_row[ox] = kept(ox, u[ox] - (anchor_x[ox] + tx));
                    }
                    if wrap {
                        // dx modulo the period, to the representative nearest the regular tap.
                        for ox in 0..wo {
                            let dx = u[ox] - (anchor_x[ox] + tx);
                            let dx = dx - period * (dx / period).round();
                            dx_row[ox] = kept(ox, dx);
                        }
                    }
                }
            }
            (bad_anchors, bad_taps)
        })
        .collect();
    let fallback_anchors = counts.iter().map(|c| c.0).sum();
    let fallback_taps = counts.iter().map(|c| c.1).sum();
    Ok(Offsets {
        data,
        kernel: geometry.kernel,
        input_size,
        output_size,
        fallback_anchors,
        fallback_taps,
    })
}

/// Feature-map sizes `[H, W]` of a U-Net pyramid of `depth` 2x2 max-poolings (floor division,
/// as PyTorch's `MaxPool2d(2)`), starting at the network input `[H, W]`.
pub fn pyramid_sizes(input: [usize; 2], depth: usize) -> Vec<[usize; 2]> {
    let mut sizes = vec![input];
    for _ in 0..depth {
        let [h, w] = *sizes.last().expect("non-empty");
        sizes.push([h / 2, w / 2]);
    }
    sizes
}

#[cfg(test)]
mod tests;
