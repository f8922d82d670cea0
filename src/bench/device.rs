//! Timings on any device, for the GPU check (`calibconv bench-device`): the calibrated layers of
//! a U-Net against `conv2d` (cuDNN on CUDA) with the same weights, and a whole U-Net training
//! step standard against calibrated, with peak memory.
//!
//! Every timing is synchronised (`cudaDeviceSynchronize` before and after on CUDA) and paired:
//! in each repetition the reference and the candidate run back to back, alternating which goes
//! first, after warm-up calls (cuDNN picks its algorithms, the caching allocator fills). Times and
//! ratios are medians over repetitions, each ratio with the distribution-free 95% interval of
//! its median (as `calibconv bench`). Peak memory is measured per variant in a child process
//! (`--memory-child`): on CUDA the device memory in use after one step minus before it, from the
//! driver (`cuMemGetInfo`: what libtorch's caching allocator reserved at the step's peak, plus
//! nothing else since the process does nothing else), on the CPU the resident-set high-water mark
//! (`VmHWM`). A layer's first input needs no gradient, as in training.

use std::time::Instant;

use serde::{Deserialize, Serialize};
use tch::nn::{Module, ModuleT, OptimizerConfig, VarStore};
use tch::{Device, Kind, Tensor};

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::kernel::{pyramid_sizes, InputFrame};
use crate::nn::{conv2d, Conv2dConfig, ConvKind, Head, UNet, UNetConfig};

/// One layer to time: `[batch, c_in, c_out, height, width]`, 3x3 "same", and whether its input
/// needs a gradient (not a network's first layer).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerSpec {
    /// `preset HxW Bn: c_in->c_out at hxw`.
    pub name: String,
    pub shape: [i64; 5],
    pub input_grad: bool,
}

/// The distinct 3x3 layers of a U-Net preset at `size` and `batch` (transposed up-sampling, as
/// `nn::unet` builds it: `inc` in -> w0 -> w0, `down l` w(l-1) -> w(l) -> w(l), `up` to level l
/// 2 w(l) -> w(l) -> w(l)).
pub fn unet_layers(preset: &str, size: [i64; 2], batch: i64) -> Result<Vec<LayerSpec>> {
    let cfg = UNetConfig::preset(preset, Head::Depth)?;
    let sizes = pyramid_sizes(size.map(|v| v as usize), cfg.depth);
    let w = |l: usize| cfg.level_width(l);
    let mut pairs = vec![(cfg.in_channels, w(0), 0), (w(0), w(0), 0)];
    for l in 1..=cfg.depth {
        pairs.extend([(w(l - 1), w(l), l), (w(l), w(l), l)]);
    }
    for l in (0..cfg.depth).rev() {
        pairs.push((2 * w(l), w(l), l));
    }
    let mut out: Vec<LayerSpec> = Vec::new();
    for (c_in, c_out, l) in pairs {
        let [h, wd] = sizes[l].map(|v| v as i64);
        let spec = LayerSpec {
            name: format!(
                "{preset} {}x{} B{batch}: {c_in}->{c_out} at {h}x{wd}",
                size[0], size[1]
            ),
            shape: [batch, c_in, c_out, h, wd],
            input_grad: !(l == 0 && c_in == cfg.in_channels),
        };
        if !out.iter().any(|o| o.shape == spec.shape) {
            out.push(spec);
        }
    }
    Ok(out)
}

/// One layer's timings (milliseconds, medians) and ratios calibrated / `conv2d`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerRow {
    pub layer: String,
    pub cudnn_ms: f64,
    pub calibrated_ms: f64,
    pub cudnn_fb_ms: f64,
    pub calibrated_fb_ms: f64,
    pub ratio_fwd: f64,
    pub ratio_fwd_ci: Option<[f64; 2]>,
    pub ratio_fb: f64,
    pub ratio_fb_ci: Option<[f64; 2]>,
    pub reps: usize,
}

/// A U-Net training step (forward, loss, backward, Adam), standard against calibrated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepRow {
    pub preset: String,
    pub batch: i64,
    pub size: [i64; 2],
    pub standard_ms: f64,
    pub calibrated_ms: f64,
    pub ratio: f64,
    pub ratio_ci: Option<[f64; 2]>,
    pub reps: usize,
    /// From the memory children (GiB); `None` where not measured.
    pub standard_peak_gib: Option<f64>,
    pub calibrated_peak_gib: Option<f64>,
}

/// Blocks until `device` has finished its queued work.
pub fn sync(device: Device) {
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
}

/// Synchronised wall time of `f` in milliseconds.
fn time_ms(device: Device, f: &mut dyn FnMut()) -> f64 {
    sync(device);
    let start = Instant::now();
    f();
    sync(device);
    start.elapsed().as_secs_f64() * 1e3
}

/// `warmup` calls of each, then `reps` paired repetitions (order alternating): the medians of
/// the reference's and the candidate's times, and of their ratios with its interval.
fn paired(
    device: Device,
    warmup: usize,
    reps: usize,
    reference: &mut dyn FnMut(),
    candidate: &mut dyn FnMut(),
) -> (f64, f64, f64, Option<[f64; 2]>) {
    for _ in 0..warmup {
        time_ms(device, reference);
        time_ms(device, candidate);
    }
    let (mut r, mut c, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..reps {
        let (a, b) = if i % 2 == 0 {
            let a = time_ms(device, reference);
            (a, time_ms(device, candidate))
        } else {
            let b = time_ms(device, candidate);
            (time_ms(device, reference), b)
        };
        r.push(a);
        c.push(b);
        ratio.push(b / a);
    }
    ratio.sort_by(|a, b| a.total_cmp(b));
    let ci = super::paired::median_ci(&ratio);
    (
        super::paired::median(r),
        super::paired::median(c),
        super::paired::median(ratio),
        ci,
    )
}

/// Times one layer on `device`: calibrated (offsets of `camera`) against `conv2d` with the same
/// weights, forward and forward + backward.
pub fn layer_row(
    camera: &Camera,
    spec: &LayerSpec,
    device: Device,
    reps: usize,
) -> Result<LayerRow> {
    let [b, c_in, c_out, h, w] = spec.shape;
    let build = |kind: &ConvKind| -> Result<(VarStore, crate::nn::Conv)> {
        let vs = VarStore::new(device);
        let conv = conv2d(
            &vs.root(),
            c_in,
            c_out,
            3,
            kind,
            [h, w],
            Conv2dConfig::default(),
        )?;
        Ok((vs, conv))
    };
    let (vs_std, standard) = build(&ConvKind::Standard)?;
    let calibrated_kind = ConvKind::Calibrated {
        camera: std::sync::Arc::new(camera.clone()),
        frame: InputFrame::default(),
    };
    let (mut vs_cal, calibrated) = build(&calibrated_kind)?;
    vs_cal.copy(&vs_std)?;
    let x =
        Tensor::randn([b, c_in, h, w], (Kind::Float, device)).set_requires_grad(spec.input_grad);
    let probe = Tensor::randn([b, c_out, h, w], (Kind::Float, device));
    let clear = |vars: &[Tensor]| {
        for v in vars.iter().chain(std::iter::once(&x)) {
            let mut g = v.grad();
            if g.defined() {
                let _ = g.zero_();
            }
        }
    };
    let (vars_std, vars_cal) = (vs_std.trainable_variables(), vs_cal.trainable_variables());
    let (s_f, c_f, r_f, ci_f) = paired(
        device,
        2,
        reps,
        &mut || drop(tch::no_grad(|| standard.forward(&x))),
        &mut || drop(tch::no_grad(|| calibrated.forward(&x))),
    );
    let (s_b, c_b, r_b, ci_b) = paired(
        device,
        2,
        reps,
        &mut || {
            (standard.forward(&x) * &probe).sum(Kind::Float).backward();
            clear(&vars_std);
        },
        &mut || {
            (calibrated.forward(&x) * &probe)
                .sum(Kind::Float)
                .backward();
            clear(&vars_cal);
        },
    );
    Ok(LayerRow {
        layer: spec.name.clone(),
        cudnn_ms: s_f,
        calibrated_ms: c_f,
        cudnn_fb_ms: s_b,
        calibrated_fb_ms: c_b,
        ratio_fwd: r_f,
        ratio_fwd_ci: ci_f,
        ratio_fb: r_b,
        ratio_fb_ci: ci_b,
        reps,
    })
}

/// A U-Net and its optimizer, ready for training steps on a fixed batch.
struct StepNet {
    vs: VarStore,
    net: UNet,
    opt: tch::nn::Optimizer,
}

impl StepNet {
    fn new(preset: &str, kind: &ConvKind, size: [i64; 2], device: Device) -> Result<Self> {
        let cfg = UNetConfig::preset(preset, Head::Depth)?;
        let vs = VarStore::new(device);
        let net = UNet::new(&vs.root(), &cfg, kind, size)?;
        let opt = tch::nn::Adam::default().build(&vs, 1e-4)?;
        Ok(Self { vs, net, opt })
    }

    fn step(&mut self, x: &Tensor, target: &Tensor) {
        let y = self.net.forward_t(x, true);
        let loss = (&y - target).abs().mean(Kind::Float);
        self.opt.zero_grad();
        loss.backward();
        self.opt.step();
    }
}

/// The fixed batch of a step benchmark: images and depth targets.
fn step_batch(batch: i64, size: [i64; 2], device: Device) -> (Tensor, Tensor) {
    tch::manual_seed(0);
    let x = Tensor::rand([batch, 3, size[0], size[1]], (Kind::Float, device));
    let t = Tensor::rand([batch, 1, size[0], size[1]], (Kind::Float, device)) * 5.0 + 0.5;
    (x, t)
}

/// The calibrated kind for `camera` (default frame).
fn calibrated_kind(camera: &Camera) -> ConvKind {
    ConvKind::Calibrated {
        camera: std::sync::Arc::new(camera.clone()),
        frame: InputFrame::default(),
    }
}

/// Times training steps of a U-Net preset, standard against calibrated, interleaved (both nets
/// live at once: their weights are small next to a step's activations).
pub fn step_row(
    camera: &Camera,
    preset: &str,
    size: [i64; 2],
    batch: i64,
    device: Device,
    reps: usize,
) -> Result<StepRow> {
    let (x, t) = step_batch(batch, size, device);
    let mut standard = StepNet::new(preset, &ConvKind::Standard, size, device)?;
    let mut calibrated = StepNet::new(preset, &calibrated_kind(camera), size, device)?;
    calibrated.vs.copy(&standard.vs)?;
    let (s, c, r, ci) = paired(device, 2, reps, &mut || standard.step(&x, &t), &mut || {
        calibrated.step(&x, &t)
    });
    Ok(StepRow {
        preset: preset.into(),
        batch,
        size,
        standard_ms: s,
        calibrated_ms: c,
        ratio: r,
        ratio_ci: ci,
        reps,
        standard_peak_gib: None,
        calibrated_peak_gib: None,
    })
}

/// The memory child: one training step of `preset` with `kernel` (`standard` or `calibrated`)
/// on `device`; returns the peak memory the step added, in GiB (see the module doc).
pub fn step_memory(
    camera: &Camera,
    preset: &str,
    kernel: &str,
    size: [i64; 2],
    batch: i64,
    device: Device,
) -> Result<f64> {
    let kind = match kernel {
        "standard" => ConvKind::Standard,
        "calibrated" => calibrated_kind(camera),
        other => {
            return Err(Error::InvalidArgument(format!(
                "kernel must be standard or calibrated, got {other}"
            )))
        }
    };
    let mut net = StepNet::new(preset, &kind, size, device)?;
    let (x, t) = step_batch(batch, size, device);
    sync(device);
    let gib = |bytes: u64| bytes as f64 / f64::from(1u32 << 30);
    if let Device::Cuda(_) = device {
        let in_use = || {
            crate::device::cuda_memory_in_use().ok_or_else(|| {
                Error::InvalidArgument(
                    "the CUDA driver did not report memory (cuMemGetInfo)".into(),
                )
            })
        };
        let before = in_use()?;
        net.step(&x, &t);
        sync(device);
        return Ok(gib(in_use()?.saturating_sub(before)));
    }
    super::proc::peak_mib(&mut || net.step(&x, &t))
        .map(|mib| mib / 1024.0)
        .ok_or_else(|| Error::InvalidArgument("no resident-set high-water mark (/proc)".into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classic_layers_at_the_paper_size_are_its_distinct_3x3_convolutions() {
        let layers = unet_layers("classic", [1088, 960], 8).unwrap();
        let shapes: Vec<_> = layers.iter().map(|l| l.shape).collect();
        assert_eq!(shapes[0], [8, 3, 64, 1088, 960]);
        assert!(!layers[0].input_grad);
        assert!(shapes.contains(&[8, 64, 64, 1088, 960]));
        assert!(shapes.contains(&[8, 512, 1024, 68, 60]));
        assert!(shapes.contains(&[8, 1024, 1024, 68, 60]));
        assert!(shapes.contains(&[8, 128, 64, 1088, 960]));
        // 2 at level 0, 2 per level down, 1 new (the concatenation) per level up.
        assert_eq!(layers.len(), 2 + 2 * 4 + 4);
    }

    #[test]
    fn layer_and_step_rows_run_on_the_cpu() {
        let camera = crate::camera::shipped("f195");
        let spec = &unet_layers("tiny", [32, 32], 2).unwrap()[1];
        let row = layer_row(&camera, spec, Device::Cpu, 3).unwrap();
        assert!(row.cudnn_ms > 0.0 && row.calibrated_fb_ms > 0.0);
        assert!(row.ratio_fwd.is_finite() && row.ratio_fb.is_finite());
        let step = step_row(&camera, "tiny", [32, 32], 2, Device::Cpu, 3).unwrap();
        assert!(step.standard_ms > 0.0 && step.ratio.is_finite());
        let gib = step_memory(&camera, "tiny", "calibrated", [32, 32], 2, Device::Cpu).unwrap();
        assert!(gib >= 0.0);
    }
}
