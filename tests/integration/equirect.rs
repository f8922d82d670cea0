//! Panoramas end to end: calibrated offsets of an equirectangular camera across its seam, the
//! deformable convolution with columns wrapping around, and the calibrated layer that uses both.

use tch::nn::{Module, VarStore};
use tch::{Device, Kind, Tensor};

use calibconv::camera::{self, Camera, CameraModel, Equirectangular};
use calibconv::kernel::{compute_offsets, InputFrame, LayerGeometry, Offsets, OffsetsTensor};
use calibconv::nn::{CalibratedConv2d, CameraInput, Conv2dConfig};
use calibconv::ops::{deform_conv2d_planned, Border, ConvGeometry, SamplingPlan};

use crate::common::max_rel;

/// Offsets are float32: a panorama's offsets reach W/2 = 32 px at the pole rows, whose float32
/// spacing is ~4e-6 px; 1e-4 px is margin, and a kernel turning by even 1 degree moves a corner
/// tap by ~0.02 px.
const OFFSET_TOL_PX: f32 = 1e-4;
/// Float64 convolutions composed in different orders: round-off ~1e-15 relative; 1e-12 is margin.
const F64_REL_TOL: f64 = 1e-12;
/// Float32 layer outputs summed in different orders: ~1e-7 relative; 1e-5 is margin.
const F32_REL_TOL: f64 = 1e-5;

fn equirect() -> Camera {
    camera::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/cameras/equirect.toml"
    ))
    .unwrap()
}

/// `dx` difference reduced modulo the feature-map width `w` to the representative nearest 0.
fn wrapped(d: f32, w: usize) -> f32 {
    let w = w as f32;
    d - w * (d / w).round()
}

/// The largest difference (dx modulo the width) between the offsets of columns `a` and `b`.
fn column_difference(off: &Offsets, row: usize, a: usize, b: usize) -> f32 {
    let [kh, kw] = off.kernel;
    let w = off.input_size[1];
    let mut worst = 0.0f32;
    for i in 0..kh {
        for j in 0..kw {
            let (pa, pb) = (off.get([i, j], [row, a]), off.get([i, j], [row, b]));
            worst = worst
                .max((pa[0] - pb[0]).abs())
                .max(wrapped(pa[1] - pb[1], w).abs());
        }
    }
    worst
}

#[test]
fn panorama_offsets_are_continuous_across_the_seam_and_the_same_in_every_column() {
    let cam = equirect();
    assert!(cam.wraps_horizontally());
    // 1024x512 at 1/16: 32 x 64.
    let size = [32, 64];
    let off = compute_offsets(&cam, size, &LayerGeometry::same(3), &InputFrame::default()).unwrap();
    assert_eq!((off.fallback_anchors, off.fallback_taps), (0, 0));
    assert!(off.data.iter().all(|v| v.is_finite()), "NaN or inf offsets");
    for row in 0..size[0] {
        // Across the seam: the last column and the first are neighbours like any other two.
        let seam = column_difference(&off, row, size[1] - 1, 0);
        assert!(seam < OFFSET_TOL_PX, "row {row}: {seam} px across the seam");
        // Rotating the panorama about the vertical axis moves every column onto another, so the
        // offsets of a row are the same everywhere (up to whole turns of dx).
        for col in 1..size[1] {
            let d = column_difference(&off, row, col, 0);
            assert!(d < OFFSET_TOL_PX, "row {row} column {col}: {d} px");
        }
        // Offsets stay small: the nearest representative modulo the width was taken.
        for k in 0..9 {
            let dx = off.get([k / 3, k % 3], [row, 0])[1];
            assert!(
                dx.abs() <= size[1] as f32 / 2.0 + 1e-3,
                "row {row} tap {k}: {dx}"
            );
        }
    }
    // The equator rows see an almost regular kernel; the pole rows a strongly deformed one whose
    // top taps cross the pole, half a turn away.
    assert!(off.get([0, 0], [16, 0])[1].abs() < 0.02);
    let over_the_pole = off.get([0, 1], [0, 0])[1];
    assert!((over_the_pole.abs() - 32.0).abs() < 0.01, "{over_the_pole}");
}

#[test]
fn a_panorama_cannot_be_padded_horizontally() {
    let frame = InputFrame {
        padding: [8, 0],
        ..Default::default()
    };
    let e = compute_offsets(&equirect(), [32, 64], &LayerGeometry::same(3), &frame).unwrap_err();
    assert!(e.to_string().contains("panorama"), "{e}");
    // Vertical padding is fine.
    let frame = InputFrame {
        padding: [0, 16],
        ..Default::default()
    };
    assert!(compute_offsets(&equirect(), [33, 64], &LayerGeometry::same(3), &frame).is_ok());
}

/// `x` padded by `p` columns on each side with the columns of the other side.
fn circular_pad_x(x: &Tensor, p: i64) -> Tensor {
    let w = x.size()[3];
    Tensor::cat(
        &[x.narrow(3, w - p, p), x.shallow_clone(), x.narrow(3, 0, p)],
        3,
    )
}

#[test]
fn wrap_x_with_zero_offsets_is_a_convolution_of_the_circularly_padded_input() {
    let _guard = tch::no_grad_guard();
    tch::manual_seed(7);
    let opts = (Kind::Double, Device::Cpu);
    // (stride, padding, dilation) with "same"-style padding in x, to be wrapped.
    for (stride, padding, dilation) in [
        ([1, 1], [1, 1], [1, 1]),
        ([2, 2], [1, 1], [1, 1]),
        ([1, 1], [2, 2], [2, 2]),
        ([1, 2], [0, 1], [1, 1]),
    ] {
        let (h, w) = (7i64, 9i64);
        let x = Tensor::randn([2, 3, h, w], opts);
        let weight = Tensor::randn([4, 3, 3, 3], opts);
        let bias = Tensor::randn([4], opts);
        let ho = (h + 2 * padding[0] - dilation[0] * 2 - 1) / stride[0] + 1;
        let wo = (w + 2 * padding[1] - dilation[1] * 2 - 1) / stride[1] + 1;
        let offsets = Tensor::zeros([18, ho, wo], opts);
        let plan = |border| {
            SamplingPlan::with_border(
                &offsets,
                [h, w],
                ConvGeometry::new([3, 3], stride, padding, dilation),
                Kind::Double,
                border,
            )
            .unwrap()
        };
        let wrapped =
            deform_conv2d_planned(&x, &plan(Border::WrapX), &weight, Some(&bias), 1).unwrap();
        let reference = circular_pad_x(&x, padding[1]).conv2d(
            &weight,
            Some(&bias),
            stride,
            [padding[0], 0],
            dilation,
            1,
        );
        let err = max_rel(&wrapped, &reference);
        assert!(
            err < F64_REL_TOL,
            "{stride:?} {padding:?} {dilation:?}: {err}"
        );
        // With zeros outside (torchvision's rule) the border columns differ.
        let zeros =
            deform_conv2d_planned(&x, &plan(Border::Zeros), &weight, Some(&bias), 1).unwrap();
        assert!(max_rel(&zeros, &reference) > 1e-3, "{stride:?} {padding:?}");
    }
}

#[test]
fn calibrated_conv_on_a_panorama_commutes_with_turning_it() {
    let _guard = tch::no_grad_guard();
    tch::manual_seed(11);
    let cam = Camera::Equirectangular(Equirectangular::new(128, 64).unwrap());
    let vs = VarStore::new(Device::Cpu);
    let size = [16i64, 32];
    let conv = CalibratedConv2d::new(
        &(vs.root() / "conv"),
        3,
        5,
        3,
        CameraInput::new(&cam, &InputFrame::default(), size),
        Conv2dConfig::default(),
    )
    .unwrap();
    let x = Tensor::randn([2, 3, size[0], size[1]], (Kind::Float, Device::Cpu));
    let y = conv.forward(&x);
    // Turning the panorama by k columns turns the output by k columns, seam included.
    for k in [1i64, 7, 31] {
        let turned = conv.forward(&x.roll([k], [3]));
        let err = max_rel(&turned, &y.roll([k], [3]));
        assert!(err < F32_REL_TOL, "turn by {k}: {err}");
    }
    // Not a trivial property: the same layer with zeros at the border does not commute.
    let zeros = SamplingPlan::new(
        &conv.offsets.to_tensor(),
        size,
        ConvGeometry::new([3, 3], [1, 1], [1, 1], [1, 1]),
        Kind::Float,
    )
    .unwrap();
    let z = deform_conv2d_planned(&x, &zeros, &conv.ws, conv.bs.as_ref(), 1).unwrap();
    let z_turned =
        deform_conv2d_planned(&x.roll([7], [3]), &zeros, &conv.ws, conv.bs.as_ref(), 1).unwrap();
    assert!(max_rel(&z_turned, &z.roll([7], [3])) > 1e-3);
}

#[test]
fn upright_frame_is_a_rotation_onto_the_ray_with_rows_along_the_parallels() {
    use calibconv::kernel::upright_frame;
    for (lon, lat) in [
        (0.0f64, 0.0f64),
        (1.0, 0.3),
        (-2.9, -1.2),
        (3.1, 1.5),
        (0.4, -0.01),
    ] {
        let r = [lat.cos() * lon.sin(), -lat.sin(), lat.cos() * lon.cos()];
        let m = upright_frame(r);
        let col = |c: usize| [m[0][c], m[1][c], m[2][c]];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        // Orthonormal columns, the third is the ray, the first horizontal (no y component).
        for a in 0..3 {
            for b in 0..3 {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((dot(col(a), col(b)) - want).abs() < 1e-12, "{lon} {lat}");
            }
        }
        assert!((0..3).all(|i| (col(2)[i] - r[i]).abs() < 1e-15));
        assert_eq!(col(0)[1], 0.0);
        // Right-handed (a rotation, not a mirror): e x d = r; d points down (+y) off the poles.
        let (e, d) = (col(0), col(1));
        let cross = [
            e[1] * d[2] - e[2] * d[1],
            e[2] * d[0] - e[0] * d[2],
            e[0] * d[1] - e[1] * d[0],
        ];
        assert!((0..3).all(|i| (cross[i] - r[i]).abs() < 1e-12));
        assert!(d[1] > 0.0);
    }
    // At the poles the longitude is arbitrary: no NaN.
    let m = upright_frame([0.0, -1.0, 0.0]);
    assert!(m.iter().flatten().all(|v| v.is_finite()));
}
