//! The crate on CUDA: the deformable op against the CPU float64 op, the plan and offsets caches
//! per device, a U-Net training step, and checkpoints moving between devices.
//!
//! Every check is a function of the device it runs on. Each test runs it on the CPU first (the
//! op through the ATen composition, the code path CUDA tensors take, so the checks themselves
//! are exercised on every machine), then on `cuda:0` where CUDA is available; elsewhere the
//! CUDA half prints `skipped: CUDA not available` and the test passes on its CPU half alone.
//! `calibconv info` says whether this build links libtorch's CUDA backend.

mod common;

use std::path::Path;
use std::sync::Arc;

use tch::nn::{Module, ModuleT, VarStore};
use tch::{Device, Kind, Tensor};

use calibconv::camera::Camera;
use calibconv::kernel::InputFrame;
use calibconv::nn::{
    CalibratedConv2d, CameraInput, Conv2dConfig, ConvKind, Head, UNet, UNetConfig,
};
use calibconv::ops::{self, Backend, ConvGeometry};
use calibconv::train::checkpoint;

use common::{checkpoint_info, max_rel};

/// float32 on the device against float64 on the CPU, relative to the largest magnitude: float32
/// round-off of sums over up to K*C = 3*3*16 = 144 products (~1e-6 measured on the CPU) with a
/// margin for cuBLAS's TF32-free but reordered sums.
const F32_TOL: f64 = 1e-4;
/// float64 on the device against float64 on the CPU: summation order only.
const F64_TOL: f64 = 1e-10;
/// A float32 U-Net step on two devices, by the norm of each gradient's difference relative to
/// its norm: a ReLU input within round-off of 0 flips between devices and its gradient with it
/// (seen at 3.5e-3 between float32 and float64 U-Nets), so elementwise comparison is not fair.
const STEP_GRAD_TOL: f64 = 5e-2;
/// The same step's loss (a mean over every pixel, float32).
const STEP_LOSS_TOL: f64 = 1e-4;

/// The devices a test runs on: the CPU, then `cuda:0` where CUDA is available (else a line
/// saying that the CUDA half was skipped).
fn devices(test: &str) -> Vec<Device> {
    let mut out = vec![Device::Cpu];
    if tch::Cuda::is_available() {
        out.push(Device::Cuda(0));
    } else {
        eprintln!("{test}: CUDA half skipped: CUDA not available (see `calibconv info`)");
    }
    out
}

/// The op's output and the gradients of input, weight and bias of `sum(y * probe)`, on the CPU
/// in float64 (the reference).
fn op_results(
    backend: Backend,
    device: Device,
    kind: Kind,
    case: &OpCase,
    t: &[Tensor; 5],
) -> Vec<Tensor> {
    let [x, off, w, b, probe] = t.each_ref().map(|v| v.to_device(device).to_kind(kind));
    let [x, w, b] = [x, w, b].map(|v| v.set_requires_grad(true));
    let plan = ops::tensor_plan(&off, case.size, case.geometry, kind, device).unwrap();
    assert_eq!(plan.device(), device);
    let y = ops::deform_conv2d_planned_with(&x, &plan, &w, Some(&b), case.groups, backend).unwrap();
    let loss = (&y * &probe).sum(kind);
    let grads = Tensor::run_backward(&[loss], &[&x, &w, &b], false, false);
    std::iter::once(y.detach())
        .chain(grads)
        .map(|v| v.to_device(Device::Cpu))
        .collect()
}

/// One random convolution: shapes and how far the offsets reach.
struct OpCase {
    batch: i64,
    c_in: i64,
    c_out: i64,
    size: [i64; 2],
    geometry: ConvGeometry,
    groups: i64,
    per_item: bool,
    /// Offsets are standard normal times this (large: many samples off the image).
    reach: f64,
}

/// A 3x3 kernel at stride 1 and padding 1.
const SAME_3X3: ConvGeometry = ConvGeometry {
    kernel: [3, 3],
    stride: [1, 1],
    padding: [1, 1],
    dilation: [1, 1],
};

impl OpCase {
    /// `batch` items of `c_in` -> `c_out` channels on a `size` map through [`SAME_3X3`], one
    /// group, the batch sharing offsets that reach about 2 px: what a case does not change.
    const fn new(batch: i64, c_in: i64, c_out: i64, size: [i64; 2]) -> Self {
        OpCase {
            batch,
            c_in,
            c_out,
            size,
            geometry: SAME_3X3,
            groups: 1,
            per_item: false,
            reach: 2.0,
        }
    }
}

const CASES: [OpCase; 5] = [
    OpCase::new(2, 8, 16, [17, 19]),
    OpCase {
        geometry: ConvGeometry {
            stride: [2, 2],
            ..SAME_3X3
        },
        groups: 3,
        reach: 1.5,
        ..OpCase::new(3, 6, 9, [16, 13])
    },
    OpCase {
        geometry: ConvGeometry {
            kernel: [3, 3],
            stride: [1, 2],
            padding: [2, 2],
            dilation: [2, 2],
        },
        groups: 2,
        per_item: true,
        reach: 3.0,
        ..OpCase::new(2, 4, 8, [15, 18])
    },
    OpCase {
        geometry: ConvGeometry {
            padding: [0, 1],
            ..SAME_3X3
        },
        reach: 12.0,
        ..OpCase::new(1, 16, 32, [9, 11])
    },
    OpCase {
        geometry: ConvGeometry {
            kernel: [1, 3],
            padding: [0, 1],
            ..SAME_3X3
        },
        ..OpCase::new(2, 3, 8, [12, 10])
    },
];

#[test]
fn op_matches_the_cpu_float64_op_on_random_plans() {
    for device in devices("op_matches_the_cpu_float64_op_on_random_plans") {
        // On the CPU the ATen composition, the path CUDA tensors take.
        let backend = if device == Device::Cpu {
            Backend::Aten
        } else {
            Backend::Auto
        };
        // float32 forward, float32 gradients, float64 anything.
        let mut worst = [0.0f64; 3];
        for (i, case) in CASES.iter().enumerate() {
            tch::manual_seed(i as i64);
            let opts = (Kind::Double, Device::Cpu);
            let [h, w] = case.size;
            let k = case.geometry.kernel;
            let [ho, wo] = case.geometry.output_size([h, w]).unwrap();
            let taps = k[0] * k[1];
            let off_shape: Vec<i64> = if case.per_item {
                vec![case.batch, 2 * taps, ho, wo]
            } else {
                vec![2 * taps, ho, wo]
            };
            let t = [
                Tensor::randn([case.batch, case.c_in, h, w], opts),
                Tensor::randn(off_shape.as_slice(), opts) * case.reach,
                Tensor::randn([case.c_out, case.c_in / case.groups, k[0], k[1]], opts),
                Tensor::randn([case.c_out], opts),
                Tensor::randn([case.batch, case.c_out, ho, wo], opts),
            ];
            let reference = op_results(Backend::Auto, Device::Cpu, Kind::Double, case, &t);
            for (kind, tol) in [(Kind::Float, F32_TOL), (Kind::Double, F64_TOL)] {
                let got = op_results(backend, device, kind, case, &t);
                for (j, (g, r)) in got.iter().zip(&reference).enumerate() {
                    let what = [
                        "output",
                        "input gradient",
                        "weight gradient",
                        "bias gradient",
                    ][j];
                    let e = max_rel(g, r);
                    assert!(
                        e < tol,
                        "{device:?} {kind:?} case {i} {what}: {e:e} >= {tol:e}"
                    );
                    let slot = match (kind, j) {
                        (Kind::Float, 0) => 0,
                        (Kind::Float, _) => 1,
                        _ => 2,
                    };
                    worst[slot] = worst[slot].max(e);
                }
            }
        }
        // tools/gpu/record.py reads this line.
        eprintln!(
            "op parity on {}: float32 forward_max_rel {:.2e}, grad_max_rel {:.2e}; float64 max_rel {:.2e}",
            calibconv::device::describe(device),
            worst[0],
            worst[1],
            worst[2]
        );
    }
}

/// The F195 fisheye of data/cameras (the copy embedded in the library, so the test executable
/// runs from any folder).
fn f195() -> Camera {
    let (path, text) = calibconv::data::synth::DEFAULT_CAMERAS[0];
    assert!(path.ends_with("f195.toml"));
    calibconv::camera::parse(text, Path::new(path)).unwrap()
}

/// The F195 fisheye as calibrated kernels in the default frame.
fn calibrated() -> ConvKind {
    ConvKind::Calibrated {
        camera: Arc::new(f195()),
        frame: InputFrame::default(),
    }
}

/// A calibrated 3x3 layer (8 -> 8 channels) for the F195 fisheye on `device`.
fn calibrated_layer(device: Device, size: [i64; 2]) -> (VarStore, CalibratedConv2d) {
    let vs = VarStore::new(device);
    let camera = f195();
    let frame = InputFrame::default();
    let input = CameraInput::new(&camera, &frame, size);
    let cfg = Conv2dConfig::default();
    let layer = CalibratedConv2d::new(&vs.root(), 8, 8, 3, input, cfg).unwrap();
    (vs, layer)
}

#[test]
fn plans_and_offsets_are_cached_per_device() {
    let size = [40i64, 48];
    let (_c, on_cpu) = calibrated_layer(Device::Cpu, size);
    for device in devices("plans_and_offsets_are_cached_per_device") {
        let (_a, a) = calibrated_layer(device, size);
        let (_b, b) = calibrated_layer(device, size);
        assert_eq!(a.device(), device);
        // Offsets are computed once for the process; plans once per device.
        assert!(Arc::ptr_eq(&a.offsets, &b.offsets));
        assert!(Arc::ptr_eq(&a.offsets, &on_cpu.offsets));
        assert!(
            a.plan().shares_storage_with(b.plan()),
            "{device:?}: plan built twice"
        );
        assert_eq!(a.plan().output_size(), on_cpu.plan().output_size());
        let frac = a.plan().frac().to_device(Device::Cpu);
        assert_eq!(max_rel(&frac, on_cpu.plan().frac()), 0.0);
        if device != Device::Cpu {
            assert!(!a.plan().shares_storage_with(on_cpu.plan()));
        }
        // The layer runs on its device and gives the CPU layer's values.
        let (vs_dev, layer) = calibrated_layer(device, size);
        let (mut vs_cpu, cpu_layer) = calibrated_layer(Device::Cpu, size);
        vs_cpu.copy(&vs_dev).unwrap();
        tch::manual_seed(5);
        let x = Tensor::randn([2, 8, size[0], size[1]], (Kind::Float, Device::Cpu));
        let y = layer.forward(&x.to_device(device)).to_device(Device::Cpu);
        let r = cpu_layer.forward(&x);
        let e = max_rel(&y, &r);
        assert!(e < F32_TOL, "{device:?}: layer forward differs by {e:e}");
    }
}

/// One SGD step of a calibrated tiny U-Net on `device` from the weights of `init`: the loss,
/// and every parameter's gradient (by name, on the CPU).
fn unet_step(device: Device, init: &VarStore, size: [i64; 2]) -> (f64, Vec<(String, Tensor)>) {
    let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
    let mut vs = VarStore::new(device);
    let net = UNet::new(&vs.root(), &cfg, &calibrated(), size).unwrap();
    vs.copy(init).unwrap();
    tch::manual_seed(7);
    let x = Tensor::rand([2, 3, size[0], size[1]], (Kind::Float, Device::Cpu)).to_device(device);
    let target =
        Tensor::rand([2, 1, size[0], size[1]], (Kind::Float, Device::Cpu)).to_device(device);
    let y = net.forward_t(&x, true);
    let loss = (&y - &target).abs().mean(Kind::Float);
    loss.backward();
    let mut grads: Vec<_> = vs
        .variables()
        .into_iter()
        .filter(|(_, v)| v.requires_grad())
        .map(|(n, v)| (n, v.grad().to_device(Device::Cpu)))
        .collect();
    grads.sort_by(|a, b| a.0.cmp(&b.0));
    (loss.double_value(&[]), grads)
}

#[test]
fn unet_training_step_matches_the_cpu() {
    let size = [48i64, 56];
    let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
    tch::manual_seed(3);
    let init = VarStore::new(Device::Cpu);
    UNet::new(&init.root(), &cfg, &calibrated(), size).unwrap();
    let (cpu_loss, cpu_grads) = unet_step(Device::Cpu, &init, size);
    for device in devices("unet_training_step_matches_the_cpu") {
        let (loss, grads) = unet_step(device, &init, size);
        assert!(
            (loss - cpu_loss).abs() <= STEP_LOSS_TOL * cpu_loss.abs(),
            "{device:?}: loss {loss} vs {cpu_loss} on the CPU"
        );
        for ((name, g), (_, r)) in grads.iter().zip(&cpu_grads) {
            let norm = r.norm().double_value(&[]);
            assert!(norm > 0.0, "{name}: zero gradient");
            let diff = (g - r).norm().double_value(&[]) / norm;
            assert!(
                diff < STEP_GRAD_TOL,
                "{device:?} {name}: gradient differs by {diff:e}"
            );
        }
    }
}

#[test]
fn checkpoints_move_between_devices() {
    let size = [32i64, 32];
    let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for device in devices("checkpoints_move_between_devices") {
        let net = |d: Device, seed: i64| {
            tch::manual_seed(seed);
            let vs = VarStore::new(d);
            UNet::new(&vs.root(), &cfg, &ConvKind::Standard, size).unwrap();
            vs
        };
        let named = |vs: &VarStore| {
            let mut v: Vec<_> = vs
                .variables()
                .into_iter()
                .map(|(n, t)| (n, t.to_device(Device::Cpu)))
                .collect();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            v
        };
        // Written on the device, read on the CPU.
        let on_device = net(device, 1);
        let path = dir.path().join("device.safetensors");
        checkpoint::save(&path, &on_device, &checkpoint_info(cfg, size)).unwrap();
        let cpu = net(Device::Cpu, 2);
        checkpoint::load(&path, &cpu, &cfg).unwrap();
        for ((n, a), (_, b)) in named(&on_device).iter().zip(&named(&cpu)) {
            assert!(a.equal(b), "{device:?} -> CPU: {n}");
        }
        // And back: written on the CPU, read on the device.
        let back = net(device, 3);
        let path = dir.path().join("cpu.safetensors");
        checkpoint::save(&path, &cpu, &checkpoint_info(cfg, size)).unwrap();
        checkpoint::load(&path, &back, &cfg).unwrap();
        for (_, t) in back.variables() {
            assert_eq!(t.device(), device);
        }
        for ((n, a), (_, b)) in named(&cpu).iter().zip(&named(&back)) {
            assert!(a.equal(b), "CPU -> {device:?}: {n}");
        }
    }
}

#[test]
fn cuda_without_cuda_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let file = common::experiment::ExperimentFile::tiny("wants-cuda")
        .set(
            "device",
            if tch::Cuda::is_available() {
                "cuda:4096"
            } else {
                "cuda"
            },
        )
        .set_toml("data.train", "{ toy = 4, split = \"train\" }")
        .write(&dir.path().join("wants-cuda.toml"));
    let err = common::failed(common::calibconv_in(
        dir.path(),
        &["train", common::s(&file)],
    ));
    common::assert_contains(&err, &[common::s(&file), "`device`", "cuda"]);
    // Nothing was written: no run directory.
    assert!(!dir.path().join("runs/wants-cuda").exists(), "{err}");
}
