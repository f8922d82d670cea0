//! The timed and measured workloads of the benchmark: one layer shape, the camera's pyramid,
//! the U-Net-shaped training step, the functional op, and the peak-memory pass.

use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

use super::proc::{cpu_seconds, peak_mib, pin_malloc_threshold};
use super::*;
use crate::camera::CameraModel;
use crate::kernel::{compute_offsets, pyramid_sizes, InputFrame, LayerGeometry, OffsetsTensor};
use crate::nn::{CalibratedConv2d, CameraInput, Conv2dConfig, ConvKind, UNet, UpMode};
use crate::ops::{
    deform_conv2d, deform_conv2d_planned_with, Backend, Border, ConvGeometry, SamplingPlan,
};

/// The camera's pyramid frame: the image padded right/bottom to a multiple of `2^depth`.
fn pyramid_frame(camera: &Camera, depth: usize) -> (InputFrame, [usize; 2]) {
    let [w, h] = camera.size();
    let m = 1usize << depth;
    let frame = InputFrame {
        padding: [(m - w % m) % m, (m - h % m) % m],
        ..Default::default()
    };
    (frame, [h + frame.padding[1], w + frame.padding[0]])
}

/// A calibrated layer with its `conv2d` twin (same weights), an input and a probe, each in the
/// layout its network gives it: NCHW for `conv2d`, channels-last for the calibrated layer (whose
/// outputs are channels-last, see `nn::CalibratedConv2d`) except at a first layer, which reads
/// the NCHW image in both networks.
struct LayerTensors {
    vs: nn::VarStore,
    conv: CalibratedConv2d,
    x: Tensor,
    probe: Tensor,
    /// `x` and `probe` as the calibrated layer sees them.
    x_cal: Tensor,
    probe_cal: Tensor,
    input_grad: bool,
}

/// A channels-last copy of `x` (a new leaf).
fn channels_last_copy(x: &Tensor) -> Tensor {
    x.detach()
        .permute([0, 2, 3, 1])
        .contiguous()
        .permute([0, 3, 1, 2])
}

impl LayerTensors {
    fn new(camera: &Camera, layer: &Layer) -> Result<Self> {
        let [b, c_in, c_out, h, w] = layer.shape;
        let opts = (Kind::Float, Device::Cpu);
        let vs = nn::VarStore::new(Device::Cpu);
        let conv = CalibratedConv2d::new(
            &vs.root(),
            c_in,
            c_out,
            3,
            CameraInput::new(camera, &InputFrame::default(), [h, w]),
            Conv2dConfig::default(),
        )?;
        let x = Tensor::randn([b, c_in, h, w], opts).set_requires_grad(layer.input_grad);
        let probe = Tensor::randn([b, c_out, h, w], opts);
        let x_cal = if layer.input_grad {
            channels_last_copy(&x).set_requires_grad(true)
        } else {
            x.shallow_clone()
        };
        let probe_cal = channels_last_copy(&probe);
        Ok(LayerTensors {
            vs,
            conv,
            x,
            probe,
            x_cal,
            probe_cal,
            input_grad: layer.input_grad,
        })
    }

    fn bias(&self) -> &Tensor {
        self.conv.bs.as_ref().expect("bias")
    }

    fn reference(&self, x: &Tensor) -> Tensor {
        x.conv2d(&self.conv.ws, Some(self.bias()), [1, 1], [1, 1], [1, 1], 1)
    }

    fn native(&self, x: &Tensor) -> Tensor {
        self.conv.forward(x)
    }

    fn aten(&self, x: &Tensor) -> Tensor {
        let plan = self.conv.plan();
        deform_conv2d_planned_with(x, plan, &self.conv.ws, Some(self.bias()), 1, Backend::Aten)
            .expect("aten composition")
    }

    /// Forward and backward of `(f(x) * probe).sum()` for the weight, the bias and (unless a
    /// first layer) the input; `cal`: with the calibrated layer's input and probe.
    fn step(&self, f: &dyn Fn(&Tensor) -> Tensor, cal: bool) {
        let (x, probe) = self.inputs(cal);
        let loss = (f(x) * probe).sum(Kind::Float);
        let mut wrt = vec![&self.conv.ws, self.bias()];
        if self.input_grad {
            wrt.push(x);
        }
        drop(Tensor::run_backward(&[loss], &wrt, false, false));
    }

    fn forward(&self, f: &dyn Fn(&Tensor) -> Tensor, cal: bool) {
        drop(f(self.inputs(cal).0));
    }

    fn inputs(&self, cal: bool) -> (&Tensor, &Tensor) {
        if cal {
            (&self.x_cal, &self.probe_cal)
        } else {
            (&self.x, &self.probe)
        }
    }
}

pub(super) fn bench_shape(camera: &Camera, layer: &Layer, args: &Options) -> Result<ShapeResult> {
    let [b, c_in, c_out, h, w] = layer.shape;
    let t = LayerTensors::new(camera, layer)?;
    let _ = &t.vs;
    let reference = |x: &Tensor| t.reference(x);
    let native = |x: &Tensor| t.native(x);
    let aten = |x: &Tensor| t.aten(x);
    // Repetitions from the reference step time.
    t.step(&reference, false);
    let t_ref = time_ms(&mut || t.step(&reference, false));
    let reps = if args.quick {
        MIN_REPS
    } else {
        ((BUDGET_S * 1e3 / t_ref).round() as usize).clamp(CI_REPS, MAX_REPS)
    };
    let (fwd_pairs, step_pairs) = if args.aten {
        (
            paired(
                reps,
                &mut || t.forward(&reference, false),
                &mut [&mut || t.forward(&native, true), &mut || {
                    t.forward(&aten, true)
                }],
            ),
            paired(
                reps,
                &mut || t.step(&reference, false),
                &mut [&mut || t.step(&native, true), &mut || t.step(&aten, true)],
            ),
        )
    } else {
        (
            paired(
                reps,
                &mut || t.forward(&reference, false),
                &mut [&mut || t.forward(&native, true)],
            ),
            paired(
                reps,
                &mut || t.step(&reference, false),
                &mut [&mut || t.step(&native, true)],
            ),
        )
    };
    let mut impls = fwd_pairs
        .into_iter()
        .zip(step_pairs)
        .map(|(forward, forward_backward)| Impl {
            forward,
            forward_backward,
            peak_mib: None,
            peak_ratio: None,
        });
    let calibrated = impls.next().expect("native measured");
    let aten = impls.next();
    Ok(ShapeResult {
        net: layer.net,
        count: layer.count,
        batch: b,
        c_in,
        c_out,
        height: h,
        width: w,
        input_grad: t.input_grad,
        reps,
        conv2d_peak_mib: None,
        goal: Goal::of(layer.net, c_in, c_out, &calibrated),
        calibrated,
        aten,
    })
}

pub(super) fn ratio(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    }
}

/// Offsets and sampling plans for every level
/// of the camera's depth-4 U-Net pyramid (3x3, stride 1, "same"), from scratch, best of three.
pub(super) fn bench_pyramid(camera: &Camera) -> Result<PyramidResult> {
    let depth = 4;
    let (frame, input) = pyramid_frame(camera, depth);
    let sizes = pyramid_sizes(input, depth);
    let anchors: usize = sizes.iter().map(|s| s[0] * s[1]).sum();
    let mut best: Option<PyramidResult> = None;
    for _ in 0..3 {
        let cpu0 = cpu_seconds();
        let start = Instant::now();
        let offsets = sizes
            .iter()
            .map(|&s| compute_offsets(camera, s, &LayerGeometry::same(3), &frame))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let offsets_s = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let mut plan_bytes = 0;
        for off in &offsets {
            let plan = SamplingPlan::from_offsets(
                off,
                ConvGeometry::for_offsets(off, [1, 1], [1, 1], [1, 1]),
                Kind::Float,
                Border::Zeros,
            )?;
            plan_bytes += plan.memory_bytes();
        }
        let plans_s = start.elapsed().as_secs_f64();
        let cpu_s = cpu_seconds().zip(cpu0).map(|(b, a)| b - a);
        let r = PyramidResult {
            input_hw: input,
            levels: sizes.len(),
            anchors,
            offsets_s,
            plans_s,
            total_s: offsets_s + plans_s,
            cpu_s,
            plan_mib: plan_bytes as f64 / (1 << 20) as f64,
        };
        if best.as_ref().is_none_or(|b| r.total_s < b.total_s) {
            best = Some(r);
        }
    }
    let r = best.expect("three runs");
    println!(
        "\npyramid {}x{} ({} levels, {} anchors x 9 taps): offsets {:.3} s + plans {:.3} s = \
         {:.3} s (best of 3; CPU time {} s), plans hold {:.0} MiB",
        r.input_hw[0],
        r.input_hw[1],
        r.levels,
        r.anchors,
        r.offsets_s,
        r.plans_s,
        r.total_s,
        fmt_opt(r.cpu_s, 3),
        r.plan_mib
    );
    Ok(r)
}

/// A U-Net of the training-step benchmark: what it stands for, batch, input (H, W), base
/// channels and depth.
#[derive(Debug, Clone, Copy)]
pub(super) struct UnetSpec {
    pub(super) label: &'static str,
    pub(super) batch: i64,
    pub(super) input: [i64; 2],
    pub(super) base: i64,
    pub(super) depth: usize,
}

/// The U-Nets whose training step the benchmark times: base 32, depth 4, B2 at 256x256 (levels
/// 256..16, 32..512 channels); `--full`: the paper's classic U-Net (base 64, 64..1024 channels);
/// `--presets`: the networks the two CPU profiles fine-tune, the quick profile's tiny U-Net
/// (base 8, depth 3) at B8, 64x64, and the study profile's small one at depth 3 (base 16) at B8,
/// 144x160 (experiments/paper/profiles/study.toml: 160 px wide, 142 px high padded by 2);
/// `--quick`: the tiny one at B1.
pub(super) fn unet_specs(args: &Options) -> Vec<UnetSpec> {
    let spec = |label, batch, input, base, depth| UnetSpec {
        label,
        batch,
        input,
        base,
        depth,
    };
    if args.quick {
        vec![spec("tiny", 1, [64, 64], 8, 3)]
    } else if args.presets {
        vec![
            spec("quick profile: tiny", 8, [64, 64], 8, 3),
            spec("study profile: small, depth 3", 8, [144, 160], 16, 3),
        ]
    } else if args.full {
        vec![spec("classic", 2, [256, 256], 64, 4)]
    } else {
        vec![spec("base 32", 2, [256, 256], 32, 4)]
    }
}

/// A training step (forward in training mode, backward, SGD update) of the project's U-Net
/// ([`UNet`], batch norm, transposed up-sampling, 8-class segmentation head) with standard and
/// with calibrated 3x3 kernels (the camera's offsets at the network's input size).
struct UnetBench {
    nets: Vec<(nn::VarStore, UNet, nn::Optimizer)>,
    x: Tensor,
}

impl UnetBench {
    fn new(camera: &Camera, spec: UnetSpec) -> Result<Self> {
        let config = UNetConfig {
            in_channels: 3,
            base: spec.base,
            depth: spec.depth,
            up: UpMode::Transposed,
            head: Head::Segmentation { classes: 8 },
        };
        let kinds = [
            ConvKind::Standard,
            ConvKind::Calibrated {
                camera: std::sync::Arc::new(camera.clone()),
                frame: InputFrame::default(),
            },
        ];
        let mut nets = Vec::new();
        for kind in &kinds {
            tch::manual_seed(0);
            let vs = nn::VarStore::new(Device::Cpu);
            let net = UNet::new(&vs.root(), &config, kind, spec.input)?;
            let opt = nn::Sgd::default().build(&vs, 1e-3)?;
            nets.push((vs, net, opt));
        }
        let x = Tensor::randn(
            [spec.batch, 3, spec.input[0], spec.input[1]],
            (Kind::Float, Device::Cpu),
        );
        Ok(UnetBench { nets, x })
    }

    /// One training step of net 0 (standard) or 1 (calibrated).
    fn step(&mut self, i: usize) {
        let (_, net, opt) = &mut self.nets[i];
        let out = net.f_forward_t(&self.x, true).expect("U-Net forward");
        opt.backward_step(&out.square().mean(Kind::Float));
    }
}

/// Leaves the process's allocator where a trainer's is after its first steps: one training step
/// of each U-Net the run times ([`unet_specs`]), standard and calibrated, then dropped. glibc
/// raises its mmap threshold to the largest mmapped block freed (up to 32 MiB), so from then on
/// blocks up to the size of the networks' activations come from recycled heap memory, as in the
/// trainer from its second step on. Without it the layer rows began in a fresh process's state
/// (every block over 128 KiB a fresh mmap, faulted in page by page) and a row's `conv2d`
/// reference ran up to 4x faster or slower depending on what the calibrated layer beside it
/// happened to free (docs/bench/cpu-kernels.md).
pub(super) fn warm_like_trainer(camera: &Camera, args: &Options) -> Result<()> {
    for spec in unet_specs(args) {
        let mut nets = UnetBench::new(camera, spec)?;
        nets.step(0);
        nets.step(1);
    }
    Ok(())
}

pub(super) fn bench_unet(camera: &Camera, args: &Options) -> Result<Vec<UnetResult>> {
    unet_specs(args)
        .into_iter()
        .map(|spec| bench_one_unet(camera, spec, args.quick))
        .collect()
}

fn bench_one_unet(camera: &Camera, spec: UnetSpec, quick: bool) -> Result<UnetResult> {
    let mut nets = UnetBench::new(camera, spec)?;
    nets.step(0);
    nets.step(1);
    let t_ref = time_ms(&mut || nets.step(0));
    let reps = if quick {
        MIN_REPS
    } else {
        ((2.0 * BUDGET_S * 1e3 / t_ref).round() as usize).clamp(CI_REPS, MAX_REPS)
    };
    let nets = std::cell::RefCell::new(nets);
    let pairs = paired(
        reps,
        &mut || nets.borrow_mut().step(0),
        &mut [&mut || nets.borrow_mut().step(1)],
    );
    let step = pairs.into_iter().next().expect("one candidate");
    let UnetSpec {
        label,
        batch,
        input,
        base,
        depth,
    } = spec;
    let r = UnetResult {
        network: label,
        what: format!(
            "nn::UNet (base {base}, depth {depth}, batch norm, transposed up-sampling, 8-class \
             head), training step with SGD"
        ),
        batch,
        input_hw: input,
        base_channels: base,
        depth,
        reps,
        step,
        conv2d_peak_mib: None,
        calibrated_peak_mib: None,
        peak_ratio: None,
    };
    println!(
        "\nU-Net ({label}) B{batch} 3x{}x{}, base {base}, depth {depth}: training step conv2d \
         {:.1} ms, calibrated {:.1} ms ({:.2}x, 95% ci {}; CPU time {}x)",
        input[0],
        input[1],
        r.step.reference_ms,
        r.step.candidate_ms,
        r.step.ratio,
        fmt_ci(r.step.ratio_ci),
        fmt_opt(r.step.cpu_ratio, 2),
    );
    Ok(r)
}

/// The functional op as a researcher's own loop calls it: `ops::deform_conv2d` with the same
/// offsets tensor every step (F195 offsets, B4, 32 -> 32, 128x128), forward+backward against
/// `conv2d` with the same weights. The plan is built on the first call and then taken from the
/// plan cache.
pub(super) fn bench_functional(camera: &Camera, args: &Options) -> Result<Paired> {
    let (b, c, h, w) = (4, 32, 128, 128);
    let opts = (Kind::Float, Device::Cpu);
    let offsets = compute_offsets(
        camera,
        [h as usize, w as usize],
        &LayerGeometry::same(3),
        &InputFrame::default(),
    )?
    .to_tensor();
    let x = Tensor::randn([b, c, h, w], opts).set_requires_grad(true);
    let weight = (Tensor::randn([c, c, 3, 3], opts) * 0.1).set_requires_grad(true);
    let bias = Tensor::zeros([c], opts).set_requires_grad(true);
    let probe = Tensor::randn([b, c, h, w], opts);
    let step = |y: Tensor| {
        let loss = (y * &probe).sum(Kind::Float);
        drop(Tensor::run_backward(
            &[loss],
            &[&x, &weight, &bias],
            false,
            false,
        ));
    };
    let reference = || step(x.conv2d(&weight, Some(&bias), [1, 1], [1, 1], [1, 1], 1));
    let functional = || {
        step(deform_conv2d(
            &x,
            &offsets,
            &weight,
            Some(&bias),
            [1, 1],
            [1, 1],
            [1, 1],
            1,
        ))
    };
    let reps = if args.quick {
        MIN_REPS
    } else {
        FUNCTIONAL_REPS
    };
    let p = paired(reps, &mut || reference(), &mut [&mut || functional()])
        .pop()
        .expect("one candidate");
    println!(
        "\nfunctional ops::deform_conv2d, one offsets tensor, B{b} {c}->{c} {h}x{w}: \
         forward+backward conv2d {:.1} ms, deform_conv2d {:.1} ms ({:.2}x, 95% ci {}; CPU time \
         {}x)",
        p.reference_ms,
        p.candidate_ms,
        p.ratio,
        fmt_ci(p.ratio_ci),
        fmt_opt(p.cpu_ratio, 2)
    );
    Ok(p)
}

/// The memory pass (`--memory-child`): pins the allocator, measures one training step per layer
/// (and of the U-Net), prints a [`MemoryReport`] as the last line of stdout. No timings.
pub fn memory_child(camera: &Camera, args: &Options) -> Result<()> {
    let layers = selected_layers(args)?;
    let unet = args.only.is_empty() || args.only.contains(&Part::Unet);
    pin_malloc_threshold();
    let mut report = MemoryReport::default();
    for layer in &layers {
        let t = LayerTensors::new(camera, layer)?;
        let reference = |x: &Tensor| t.reference(x);
        let native = |x: &Tensor| t.native(x);
        let aten = |x: &Tensor| t.aten(x);
        t.step(&reference, false); // warm-up: allocations that persist across steps
        let r = peak_mib(&mut || t.step(&reference, false));
        t.step(&native, true);
        let c = peak_mib(&mut || t.step(&native, true));
        let a = if args.aten {
            t.step(&aten, true);
            peak_mib(&mut || t.step(&aten, true))
        } else {
            None
        };
        report.layers.push([r, c, a]);
    }
    if unet {
        for spec in unet_specs(args) {
            let mut nets = UnetBench::new(camera, spec)?;
            nets.step(0);
            let r = peak_mib(&mut || nets.step(0));
            nets.step(1);
            let c = peak_mib(&mut || nets.step(1));
            report.unet.push([r, c]);
        }
    }
    println!(
        "{}",
        serde_json::to_string(&report).expect("a memory report serializes")
    );
    Ok(())
}
