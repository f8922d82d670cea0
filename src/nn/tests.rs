use std::sync::Arc;

use tch::nn::{Module, VarStore};
use tch::{Device, Kind, Tensor};

use super::*;
use crate::camera::{Camera, Intrinsics, Pinhole};
use crate::kernel::InputFrame;

/// The F195 fisheye of `data/cameras/` (shared with the U-Net tests).
pub(super) fn f195() -> Camera {
    crate::camera::shipped("f195")
}

/// Calibrated kernels for `camera` in the default frame.
pub(super) fn calibrated(camera: Camera) -> ConvKind {
    ConvKind::Calibrated {
        camera: Arc::new(camera),
        frame: InputFrame::default(),
    }
}

/// The parameters of `vs`, sorted by name.
pub(super) fn names_and_shapes(vs: &VarStore) -> Vec<(String, Vec<i64>)> {
    let mut v: Vec<_> = vs
        .variables()
        .into_iter()
        .map(|(n, t)| (n, t.size()))
        .collect();
    v.sort();
    v
}

#[test]
fn both_kinds_have_identical_parameters_and_weights_move_between_them() {
    let build = |kind: &ConvKind| {
        let vs = VarStore::new(Device::Cpu);
        let conv = conv2d(
            &(vs.root() / "enc"),
            3,
            8,
            3,
            kind,
            [24, 27],
            Conv2dConfig::default(),
        )
        .unwrap();
        (vs, conv)
    };
    let (vs_std, conv_std) = build(&ConvKind::Standard);
    let (mut vs_cal, conv_cal) = build(&calibrated(f195()));
    assert_eq!(names_and_shapes(&vs_std), names_and_shapes(&vs_cal));
    vs_cal.copy(&vs_std).unwrap();
    assert!(conv_cal.weight().equal(conv_std.weight()));
    let x = Tensor::randn([2, 3, 24, 27], (Kind::Float, Device::Cpu));
    let (a, b) = (conv_std.forward(&x), conv_cal.forward(&x));
    assert_eq!(a.size(), b.size());
    // Calibrated kernels really sample elsewhere on a 195 deg fisheye.
    assert!((&a - &b).abs().max().double_value(&[]) > 1e-3);
}

#[test]
fn pinhole_with_matching_focal_is_close_to_standard_conv() {
    // A narrow pinhole: the virtual kernel focal d = k / (2 tan(k fov / 2W)) is within 0.1% of
    // fx in the centre, so sampling differs from the regular grid by well under a pixel.
    let cam = Camera::Pinhole(
        Pinhole::new(Intrinsics {
            fx: 200.0,
            fy: 200.0,
            cx: 31.5,
            cy: 31.5,
            width: 64,
            height: 64,
        })
        .unwrap(),
    );
    let vs = VarStore::new(Device::Cpu);
    let cal = conv2d(
        &vs.root(),
        2,
        4,
        3,
        &calibrated(cam),
        [64, 64],
        Conv2dConfig::default(),
    )
    .unwrap();
    let Conv::Calibrated(c) = &cal else {
        panic!("expected a calibrated conv")
    };
    // Centre anchor (31, 31) is 0.5 px from the principal point: offsets there are tiny.
    for tap in [[0, 0], [0, 2], [2, 0], [2, 2]] {
        let [dy, dx] = c.offsets.get(tap, [31, 31]);
        assert!(
            dy.abs() < 0.01 && dx.abs() < 0.01,
            "tap {tap:?}: ({dy}, {dx})"
        );
    }
}

#[test]
fn every_parameter_receives_a_gradient() {
    let vs = VarStore::new(Device::Cpu);
    let cfg = Conv2dConfig {
        stride: [2, 2],
        ..Default::default()
    };
    let conv = conv2d(&vs.root(), 3, 5, 3, &calibrated(f195()), [30, 34], cfg).unwrap();
    let x = Tensor::randn([2, 3, 30, 34], (Kind::Float, Device::Cpu));
    let y = conv.forward(&x);
    assert_eq!(y.size(), [2, 5, 15, 17]);
    assert_eq!(y.isnan().any().int64_value(&[]), 0);
    y.square().sum(Kind::Float).backward();
    for (name, t) in vs.variables() {
        let g = t.grad();
        assert!(
            g.defined() && g.abs().sum(Kind::Float).double_value(&[]) > 0.0,
            "{name} has no gradient"
        );
    }
}

#[test]
#[should_panic(expected = "offsets were built for 30x34")]
fn wrong_input_size_panics_with_a_clear_message() {
    let vs = VarStore::new(Device::Cpu);
    let conv = conv2d(
        &vs.root(),
        3,
        5,
        3,
        &calibrated(f195()),
        [30, 34],
        Conv2dConfig::default(),
    )
    .unwrap();
    let _ = conv.forward(&Tensor::zeros([1, 3, 32, 32], (Kind::Float, Device::Cpu)));
}

#[test]
fn layers_of_the_same_geometry_share_offsets_and_plans() {
    let vs = VarStore::new(Device::Cpu);
    let kind = calibrated(f195());
    let layer = |name: &str, c_in| {
        conv2d(
            &(vs.root() / name),
            c_in,
            4,
            3,
            &kind,
            [40, 44],
            Conv2dConfig::default(),
        )
        .unwrap()
    };
    let (a, b) = (layer("a", 3), layer("b", 4));
    let (Conv::Calibrated(a), Conv::Calibrated(b)) = (&a, &b) else {
        panic!("calibrated")
    };
    assert!(Arc::ptr_eq(&a.offsets, &b.offsets));
    assert!(a.plan().shares_storage_with(b.plan()));
}
