use super::*;
use crate::camera::{Intrinsics, KannalaBrandt, Pinhole};
use crate::vec3::rotate;

/// Offsets are stored as f32: 1e-4 px covers rounding of values up to ~100 px.
const OFFSET_TOL: f32 = 1e-4;

fn symmetric_kb() -> Camera {
    // Principal point at the exact image centre in the pixel-centre convention.
    let intrinsics = Intrinsics::from_parts([40.0, 40.0, 63.5, 47.5], [128, 96]);
    Camera::KannalaBrandt(KannalaBrandt::new(intrinsics, [0.0, -0.01, 0.0, 0.0], 195.0).unwrap())
}

/// The offsets of a 3x3 "same" layer on a `size` map, no padding frame.
fn offsets_3x3(cam: &Camera, size: [usize; 2]) -> Result<Offsets> {
    compute_offsets(cam, size, &LayerGeometry::same(3), &InputFrame::default())
}

#[test]
fn rotation_takes_the_optical_axis_to_the_ray() {
    for r in [
        [0.0, 0.0, 1.0],
        [0.6, 0.0, 0.8],
        [0.0, -0.6, -0.8],
        [0.0, 0.0, -1.0],
        [0.48, 0.6, 0.64],
    ] {
        let m = align_optical_axis(r);
        let z = rotate(&m, [0.0, 0.0, 1.0]);
        for a in 0..3 {
            assert!((z[a] - r[a]).abs() < 1e-12, "{r:?} -> {z:?}");
        }
        // Orthonormal: columns have unit length and are orthogonal.
        for (i, j) in [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)] {
            let dot: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            assert!((dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
        }
    }
}

#[test]
fn pinhole_offsets_at_the_principal_point_are_the_focal_mismatch() {
    // At the principal point the rotation is the identity, so tap (i, j) lands at
    // (fx / d) (i, j): its offset is (fx / d - 1) (i, j), which is near zero for a narrow
    // pinhole (the kernel maps the FOV linearly to pixels, a pinhole does not, so they never
    // match exactly).
    let (w, h) = (101usize, 101usize);
    let fx = 300.0;
    let cam = Camera::Pinhole(
        Pinhole::new(Intrinsics {
            fx,
            fy: fx,
            cx: 50.0,
            cy: 50.0,
            width: w,
            height: h,
        })
        .unwrap(),
    );
    let d = kernel_focal(3, cam.fov(), w).unwrap();
    let ratio = fx / d - 1.0;
    assert!(ratio.abs() < 0.01, "focal mismatch {ratio}");
    let off = offsets_3x3(&cam, [h, w]).unwrap();
    for i in 0..3 {
        for j in 0..3 {
            let [dy, dx] = off.get([i, j], [50, 50]);
            let (ey, ex) = (ratio * (i as f64 - 1.0), ratio * (j as f64 - 1.0));
            assert!(
                (dy as f64 - ey).abs() < 1e-6 && (dx as f64 - ex).abs() < 1e-6,
                "tap ({i},{j}): ({dy}, {dx}) vs ({ey}, {ex})"
            );
        }
    }
    assert_eq!(off.fallback_anchors, 0);
}

#[test]
fn offsets_are_mirror_symmetric_about_the_principal_point() {
    let cam = symmetric_kb();
    let off = offsets_3x3(&cam, [96, 128]).unwrap();
    let [ho, wo] = off.output_size;
    for oy in (0..ho).step_by(7) {
        for ox in (0..wo).step_by(5) {
            for i in 0..3 {
                for j in 0..3 {
                    let [dy, dx] = off.get([i, j], [oy, ox]);
                    // Left-right mirror: column ox -> wo-1-ox, tap j -> 2-j, dx -> -dx.
                    let [my, mx] = off.get([i, 2 - j], [oy, wo - 1 - ox]);
                    assert!((dy - my).abs() < OFFSET_TOL && (dx + mx).abs() < OFFSET_TOL);
                    // Up-down mirror.
                    let [ny, nx] = off.get([2 - i, j], [ho - 1 - oy, ox]);
                    assert!((dy + ny).abs() < OFFSET_TOL && (dx - nx).abs() < OFFSET_TOL);
                }
            }
        }
    }
    // The centre tap sits on the anchor.
    assert!(off
        .get([1, 1], [10, 10])
        .iter()
        .all(|v| v.abs() < OFFSET_TOL));
}

#[test]
fn stride_two_offsets_match_stride_one_at_the_same_anchors() {
    // Output (oy, ox) of a stride-2 layer has the same anchor as output (2oy, 2ox) at stride 1,
    // so its offsets must be identical; the output grid has PyTorch's size.
    let cam = symmetric_kb();
    let frame = InputFrame::default();
    let s1 = compute_offsets(&cam, [96, 128], &LayerGeometry::same(3), &frame).unwrap();
    let g2 = LayerGeometry {
        stride: [2, 2],
        ..LayerGeometry::same(3)
    };
    let s2 = compute_offsets(&cam, [96, 128], &g2, &frame).unwrap();
    assert_eq!(s2.output_size, [48, 64]);
    for oy in 0..48 {
        for ox in 0..64 {
            for tap in [[0, 0], [1, 2], [2, 1]] {
                assert_eq!(s2.get(tap, [oy, ox]), s1.get(tap, [2 * oy, 2 * ox]));
            }
        }
    }
    // Stride 2 without padding: anchors move by one pixel.
    let g3 = LayerGeometry {
        stride: [2, 2],
        padding: [0, 0],
        ..LayerGeometry::same(3)
    };
    let s3 = compute_offsets(&cam, [96, 128], &g3, &frame).unwrap();
    assert_eq!(s3.output_size, [47, 63]);
    assert_eq!(s3.get([0, 0], [3, 4]), s1.get([0, 0], [7, 9]));
}

#[test]
fn dilation_scales_the_virtual_kernel() {
    // Near the centre, a dilated kernel's taps sit about `dilation` times farther out.
    let cam = symmetric_kb();
    let g = LayerGeometry {
        dilation: [2, 2],
        padding: [2, 2],
        ..LayerGeometry::same(3)
    };
    let off = compute_offsets(&cam, [96, 128], &g, &InputFrame::default()).unwrap();
    assert_eq!(off.output_size, [96, 128]);
    let one = offsets_3x3(&cam, [96, 128]).unwrap();
    let [dy2, _] = off.get([0, 1], [47, 63]);
    let [dy1, _] = one.get([0, 1], [47, 63]);
    assert!((dy2 - 2.0 * dy1).abs() < 0.05, "{dy2} vs 2 x {dy1}");
}

#[test]
fn conventions_differ_by_the_half_pixel_shift() {
    let cam = symmetric_kb();
    let g = LayerGeometry::same(3);
    let half = compute_offsets(&cam, [24, 32], &g, &InputFrame::default()).unwrap();
    let paper_frame = InputFrame {
        convention: PixelConvention::Paper,
        ..Default::default()
    };
    let paper = compute_offsets(&cam, [24, 32], &g, &paper_frame).unwrap();
    // At 1/4 scale the paper convention moves the centre by (s - 1)/2 = -0.375 px.
    let diff = half
        .data
        .iter()
        .zip(&paper.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(diff > 1e-3, "conventions should differ");
    // Half-pixel keeps the mirror symmetry of a centred camera; the paper convention breaks it.
    let [ho, wo] = half.output_size;
    let asym =
        |o: &Offsets| (o.get([1, 0], [ho / 2, 3])[1] + o.get([1, 2], [ho / 2, wo - 4])[1]).abs();
    assert!(asym(&half) < OFFSET_TOL);
    assert!(asym(&paper) > 1e-3);
}

/// (The cache's half of this test, `deterministic_and_cached`, lives with the cache in
/// `calibconv::kernel`.)
#[test]
fn deterministic() {
    let cam = symmetric_kb();
    let g = LayerGeometry::same(5);
    let a = compute_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
    let b = compute_offsets(&cam, [48, 64], &g, &InputFrame::default()).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.shape(), [50, 48, 64]);
    assert_eq!(a.data.len(), a.shape().iter().product::<usize>());
}

#[test]
fn too_small_feature_maps_are_rejected_clearly() {
    let cam = symmetric_kb();
    let e = offsets_3x3(&cam, [3, 3]).unwrap_err();
    assert!(e.to_string().contains("feature map"), "{e}");
    let even = LayerGeometry {
        kernel: [2, 2],
        ..LayerGeometry::same(3)
    };
    assert!(compute_offsets(&cam, [32, 32], &even, &InputFrame::default()).is_err());
}

#[test]
fn pyramid_sizes_floor_like_maxpool() {
    assert_eq!(
        pyramid_sizes([960, 1082], 4),
        vec![[960, 1082], [480, 541], [240, 270], [120, 135], [60, 67]]
    );
}

#[test]
fn offsets_too_large_to_hold_are_refused_naming_the_size() {
    let cam = symmetric_kb();
    let e = offsets_3x3(&cam, [100_000, 100_000]).unwrap_err();
    assert!(matches!(e, Error::InvalidArgument(_)), "{e}");
    assert!(e.to_string().contains("100000x100000"), "{e}");
    // Sizes that overflow `usize` are refused too, not wrapped.
    let huge = LayerGeometry {
        padding: [usize::MAX / 2 + 1; 2],
        ..LayerGeometry::same(3)
    };
    assert!(compute_offsets(&cam, [32, 32], &huge, &InputFrame::default()).is_err());
    assert_eq!(huge.output_size([32, 32]), None);
}

/// The offsets by the rule of the module docs, ray by ray through `CameraModel::project` (what
/// `compute_offsets` computed before it projected whole columns).
fn offsets_ray_by_ray(
    camera: &Camera,
    input_size: [usize; 2],
    g: &LayerGeometry,
    frame: &InputFrame,
) -> Offsets {
    let [ho, wo] = g.output_size(input_size).unwrap();
    let [w_c, h_c] = camera.size();
    let scale = [
        input_size[1] as f64 / (w_c + frame.padding[0]) as f64,
        input_size[0] as f64 / (h_c + frame.padding[1]) as f64,
    ];
    let cam = camera.rescaled(scale, frame.convention);
    let [kh, kw] = g.kernel;
    let d = kernel_focal(kw, camera.fov(), input_size[1]).unwrap();
    let plane = ho * wo;
    let mut data = vec![0.0f32; 2 * kh * kw * plane];
    let (mut bad_anchors, mut bad_taps) = (0, 0);
    let period = input_size[1] as f64;
    for oy in 0..ho {
        for ox in 0..wo {
            let ay = (oy * g.stride[0] + (kh - 1) / 2 * g.dilation[0]) as f64 - g.padding[0] as f64;
            let ax = (ox * g.stride[1] + (kw - 1) / 2 * g.dilation[1]) as f64 - g.padding[1] as f64;
            let Some(ray) = cam.unproject([ax, ay]) else {
                bad_anchors += 1;
                continue;
            };
            let rot = match camera.kernel_frame() {
                KernelFrame::MinimalRotation => align_optical_axis(ray),
                KernelFrame::Upright => upright_frame(ray),
            };
            for i in 0..kh {
                let ty = (i as f64 - ((kh - 1) / 2) as f64) * g.dilation[0] as f64;
                for j in 0..kw {
                    let tx = (j as f64 - ((kw - 1) / 2) as f64) * g.dilation[1] as f64;
                    let k = i * kw + j;
                    let Some([u, v]) = cam.project(rotate(&rot, [tx, ty, d])) else {
                        bad_taps += 1;
                        continue;
                    };
                    let mut dx = u - (ax + tx);
                    if camera.wraps_horizontally() {
                        dx -= period * (dx / period).round();
                    }
                    data[2 * k * plane + oy * wo + ox] = (v - (ay + ty)) as f32;
                    data[(2 * k + 1) * plane + oy * wo + ox] = dx as f32;
                }
            }
        }
    }
    Offsets {
        data,
        kernel: g.kernel,
        input_size,
        output_size: [ho, wo],
        fallback_anchors: bad_anchors,
        fallback_taps: bad_taps,
    }
}

#[test]
fn offsets_are_the_ray_by_ray_rule_bit_for_bit() {
    // Kannala-Brandt projects whole columns (vectorised), the other models ray by ray: both give
    // the bits of the per-ray rule, fallbacks included (the folding lens loses anchors outside
    // its image circle and taps past its fold), for strides, dilations, wide kernels, a padded
    // frame and the panorama's wrap.
    let folding = Camera::KannalaBrandt(KannalaBrandt::unchecked(
        Intrinsics::from_parts([30.0, 30.0, 63.5, 47.5], [128, 96]),
        [-0.5, 0.0, 0.0, 0.0],
        90.0,
    ));
    let pinhole = Camera::Pinhole(
        Pinhole::new(Intrinsics::from_parts([50.0, 50.0, 63.5, 47.5], [128, 96])).unwrap(),
    );
    let panorama = Camera::Equirectangular(crate::camera::Equirectangular::new(128, 64).unwrap());
    let strided = LayerGeometry {
        kernel: [5, 3],
        stride: [2, 1],
        padding: [1, 2],
        dilation: [1, 2],
    };
    let padded = InputFrame {
        padding: [0, 8],
        ..Default::default()
    };
    let mut fallbacks = [0, 0];
    for (cam, size, g, frame) in [
        (
            symmetric_kb(),
            [48, 64],
            LayerGeometry::same(3),
            InputFrame::default(),
        ),
        (symmetric_kb(), [24, 32], strided, padded),
        (
            folding.clone(),
            [96, 128],
            LayerGeometry::same(3),
            InputFrame::default(),
        ),
        (folding.clone(), [48, 64], strided, padded),
        // A width that is no multiple of 4: Kannala-Brandt unprojects the last anchors alone.
        (
            folding,
            [47, 61],
            LayerGeometry::same(3),
            InputFrame::default(),
        ),
        (pinhole, [48, 64], strided, InputFrame::default()),
        (
            panorama,
            [32, 64],
            LayerGeometry::same(3),
            InputFrame::default(),
        ),
    ] {
        let got = compute_offsets(&cam, size, &g, &frame).unwrap();
        let want = offsets_ray_by_ray(&cam, size, &g, &frame);
        let bits = |o: &Offsets| o.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert!(
            bits(&got) == bits(&want),
            "{} {size:?} {g:?}",
            cam.model_name()
        );
        assert_eq!(
            (got.fallback_anchors, got.fallback_taps),
            (want.fallback_anchors, want.fallback_taps)
        );
        fallbacks[0] += got.fallback_anchors;
        fallbacks[1] += got.fallback_taps;
    }
    assert!(fallbacks[0] > 0 && fallbacks[1] > 0, "{fallbacks:?}");
}
