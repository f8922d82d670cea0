//! `calibconv bench`: the calibrated convolution against `conv2d`, interleaved in one process.
//!
//! Timings on a shared machine drift with the load, so every measurement is paired: within one
//! repetition the reference (`conv2d`, same weights) and the candidate run back to back (the
//! order alternates between repetitions), and the reported ratio is the median of the
//! per-repetition ratios. Times are medians too. Nothing here is asserted anywhere: these are
//! numbers for people.
//!
//! Peak memory: on Linux the kernel's per-process high-water mark `VmHWM` is reset by writing
//! `5` to `/proc/self/clear_refs`; a measurement is `VmHWM` after one training step minus
//! `VmRSS` before it, i.e. the resident memory the step added at its peak (inputs, weights and
//! the probe are allocated before and not counted). glibc's dynamic mmap threshold is pinned
//! first (`mallopt`), so freed tensors go back to the kernel instead of lingering in the heap
//! and hiding later allocations. Limits: page granularity, process-wide (any thread's memory
//! counts), and memory the allocator keeps cached from earlier steps is not seen again.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::Serialize;
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

use calibconv::camera::{Camera, CameraModel};
use calibconv::io::write_bytes_atomic;
use calibconv::kernel::{compute_offsets, pyramid_sizes, InputFrame, LayerGeometry};
use calibconv::nn::{CalibratedConv2d, Conv2dConfig, ConvKind, Head, UNet, UNetConfig, UpMode};
use calibconv::ops::{deform_conv2d_planned_with, Backend, Border, SamplingPlan};

use super::load_camera;
use crate::cli::{BenchArgs, BenchPart};

/// One layer shape: `[batch, c_in, c_out, height, width]` (3x3, stride 1, "same" padding).
type Shape = [i64; 5];

/// `--quick`: a smoke run of a few seconds.
const QUICK: &[Shape] = &[
    [1, 32, 32, 64, 64],
    [2, 64, 64, 32, 32],
    [1, 128, 128, 16, 16],
];
/// The default table: the levels of a U-Net with 32..512 channels at 256x256, at batch 2, and
/// the extremes of batch size.
const DEFAULT: &[Shape] = &[
    [2, 32, 32, 256, 256],
    [2, 64, 64, 128, 128],
    [2, 128, 128, 64, 64],
    [2, 256, 256, 32, 32],
    [2, 512, 512, 16, 16],
    [1, 32, 32, 256, 256],
    [1, 128, 128, 64, 64],
    [8, 64, 64, 128, 128],
    [8, 512, 512, 16, 16],
    [4, 32, 64, 128, 128],
];
/// Seconds of reference (`conv2d` training steps) spent per shape, which sets the repetitions.
const BUDGET_S: f64 = 1.5;
const MIN_REPS: usize = 3;
const MAX_REPS: usize = 15;

/// `--full`: every U-Net level at batch 1, 4 and 8.
fn full_shapes() -> Vec<Shape> {
    let levels = [(32, 256), (64, 128), (128, 64), (256, 32), (512, 16)];
    [1, 4, 8]
        .iter()
        .flat_map(|&b| levels.iter().map(move |&(c, s)| [b, c, c, s, s]))
        .collect()
}

/// Medians of a paired measurement (milliseconds) and of the per-repetition ratios.
#[derive(Debug, Serialize)]
struct Paired {
    reference_ms: f64,
    candidate_ms: f64,
    ratio: f64,
}

#[derive(Debug, Serialize)]
struct Impl {
    forward: Paired,
    forward_backward: Paired,
    /// Peak resident memory added by one training step (MiB), and its ratio to `conv2d`'s.
    peak_mib: Option<f64>,
    peak_ratio: Option<f64>,
}

#[derive(Debug, Serialize)]
struct ShapeResult {
    batch: i64,
    c_in: i64,
    c_out: i64,
    height: i64,
    width: i64,
    reps: usize,
    conv2d_peak_mib: Option<f64>,
    /// The default implementation (native kernels on the CPU).
    calibrated: Impl,
    /// The ATen composition (`--aten`), the CUDA path and the pre-native CPU path.
    aten: Option<Impl>,
}

#[derive(Debug, Serialize)]
struct PyramidResult {
    input_hw: [usize; 2],
    levels: usize,
    anchors: usize,
    offsets_s: f64,
    plans_s: f64,
    total_s: f64,
    /// CPU time of all threads (user + system) for offsets and plans: on a loaded machine,
    /// `cpu_s / threads` estimates the wall time of an idle one.
    cpu_s: Option<f64>,
    plan_mib: f64,
}

#[derive(Debug, Serialize)]
struct UnetResult {
    what: String,
    batch: i64,
    input_hw: [i64; 2],
    base_channels: i64,
    depth: usize,
    reps: usize,
    step: Paired,
    conv2d_peak_mib: Option<f64>,
    calibrated_peak_mib: Option<f64>,
    peak_ratio: Option<f64>,
}

#[derive(Debug, Serialize)]
struct Report {
    threads: i32,
    note: &'static str,
    shapes: Vec<ShapeResult>,
    pyramid: Option<PyramidResult>,
    unet: Option<UnetResult>,
}

pub fn run(args: BenchArgs) -> Result<()> {
    if args.quick && args.full {
        bail!("--quick and --full exclude each other");
    }
    tch::manual_seed(0);
    pin_malloc_threshold();
    let camera = load_camera(&args.camera)?;
    let threads = tch::get_num_threads();
    println!(
        "calibconv bench: {threads} libtorch threads, camera {}; ratios are calibrated / conv2d \
         (medians of paired, interleaved runs)",
        args.camera.display()
    );
    let run_part = |p: BenchPart| args.only.is_empty() || args.only.contains(&p);
    let shapes: Vec<Shape> = if !run_part(BenchPart::Layers) {
        Vec::new()
    } else if !args.shapes.is_empty() {
        args.shapes.clone()
    } else if args.quick {
        QUICK.to_vec()
    } else if args.full {
        full_shapes()
    } else {
        DEFAULT.to_vec()
    };
    if !shapes.is_empty() {
        print_header(args.aten);
    }
    let mut results = Vec::new();
    for &shape in &shapes {
        let r = bench_shape(&camera, shape, &args)?;
        print_row(&r);
        results.push(r);
    }
    // The full-resolution pyramid takes seconds: not part of --quick unless asked for.
    let pyramid = if run_part(BenchPart::Pyramid) && !(args.quick && args.only.is_empty()) {
        Some(bench_pyramid(&camera)?)
    } else {
        None
    };
    let unet = if run_part(BenchPart::Unet) {
        Some(bench_unet(&camera, &args)?)
    } else {
        None
    };
    let report = Report {
        threads,
        note: "ratios = medians of per-repetition (calibrated / conv2d) times, interleaved; \
               peak = VmHWM - VmRSS around one training step",
        shapes: results,
        pyramid,
        unet,
    };
    if let Some(path) = &args.json {
        write_json(path, &report)?;
        println!("\nwrote {}", path.display());
    }
    Ok(())
}

fn write_json(path: &Path, report: &Report) -> Result<()> {
    let text = serde_json::to_string_pretty(report)?;
    write_bytes_atomic(path, text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    v.map_or("-".to_string(), |v| format!("{v:.prec$}"))
}

fn print_header(aten: bool) {
    println!(
        "\n{:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5} | {:>8} {:>8} {:>5} | {:>7} {:>7} {:>5}{}",
        "B",
        "Cin",
        "Cout",
        "HxW",
        "conv fwd",
        "cal fwd",
        "x",
        "conv f+b",
        "cal f+b",
        "x",
        "conv MB",
        "cal MB",
        "x",
        if aten {
            " | aten fwd x  f+b x  mem x"
        } else {
            ""
        }
    );
}

fn print_row(r: &ShapeResult) {
    let c = &r.calibrated;
    let mut line = format!(
        "{:>2} {:>4} {:>4} {:>8} | {:>8.2} {:>8.2} {:>5.2} | {:>8.2} {:>8.2} {:>5.2} | \
         {:>7} {:>7} {:>5}",
        r.batch,
        r.c_in,
        r.c_out,
        format!("{}x{}", r.height, r.width),
        c.forward.reference_ms,
        c.forward.candidate_ms,
        c.forward.ratio,
        c.forward_backward.reference_ms,
        c.forward_backward.candidate_ms,
        c.forward_backward.ratio,
        fmt_opt(r.conv2d_peak_mib, 1),
        fmt_opt(c.peak_mib, 1),
        fmt_opt(c.peak_ratio, 2),
    );
    if let Some(a) = &r.aten {
        line.push_str(&format!(
            " | {:>10.2} {:>6.2} {:>6}",
            a.forward.ratio,
            a.forward_backward.ratio,
            fmt_opt(a.peak_ratio, 2)
        ));
    }
    println!("{line}");
}

/// Wall time of `f` in milliseconds.
fn time_ms(f: &mut dyn FnMut()) -> f64 {
    let start = Instant::now();
    f();
    start.elapsed().as_secs_f64() * 1e3
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Runs `reference` and every candidate `reps` times, interleaved (the order rotates each
/// repetition), after one warm-up call each; returns one [`Paired`] per candidate.
fn paired(
    reps: usize,
    reference: &mut dyn FnMut(),
    candidates: &mut [&mut dyn FnMut()],
) -> Vec<Paired> {
    reference();
    for c in candidates.iter_mut() {
        c();
    }
    let n = candidates.len();
    let mut ref_ms = Vec::with_capacity(reps);
    let mut cand_ms = vec![Vec::with_capacity(reps); n];
    for rep in 0..reps {
        // Slot 0 is the reference; rotate who goes first.
        let mut times = vec![0.0; n + 1];
        for k in 0..=n {
            let slot = (k + rep) % (n + 1);
            times[slot] = if slot == 0 {
                time_ms(reference)
            } else {
                time_ms(candidates[slot - 1])
            };
        }
        ref_ms.push(times[0]);
        for (i, t) in times[1..].iter().enumerate() {
            cand_ms[i].push(*t);
        }
    }
    cand_ms
        .into_iter()
        .map(|c| Paired {
            reference_ms: median(ref_ms.clone()),
            candidate_ms: median(c.clone()),
            ratio: median(c.iter().zip(&ref_ms).map(|(c, r)| c / r).collect()),
        })
        .collect()
}

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

fn bench_shape(camera: &Camera, shape: Shape, args: &BenchArgs) -> Result<ShapeResult> {
    let [b, c_in, c_out, h, w] = shape;
    let opts = (Kind::Float, Device::Cpu);
    let vs = nn::VarStore::new(Device::Cpu);
    let conv = CalibratedConv2d::new(
        &vs.root(),
        c_in,
        c_out,
        3,
        camera,
        &InputFrame::default(),
        [h, w],
        Conv2dConfig::default(),
    )?;
    let x = Tensor::randn([b, c_in, h, w], opts).set_requires_grad(true);
    let probe = Tensor::randn([b, c_out, h, w], opts);
    let bias = conv.bs.as_ref().expect("bias");
    let reference = |x: &Tensor| x.conv2d(&conv.ws, Some(bias), [1, 1], [1, 1], [1, 1], 1);
    let native = |x: &Tensor| conv.forward(x);
    let aten = |x: &Tensor| {
        deform_conv2d_planned_with(x, conv.plan(), &conv.ws, Some(bias), 1, Backend::Aten)
            .expect("aten composition")
    };
    let step = |f: &dyn Fn(&Tensor) -> Tensor| {
        let loss = (f(&x) * &probe).sum(Kind::Float);
        let grads = Tensor::run_backward(&[loss], &[&x, &conv.ws, bias], false, false);
        drop(grads);
    };
    // Repetitions from the reference step time.
    step(&reference);
    let t_ref = time_ms(&mut || step(&reference));
    let reps = if args.quick {
        MIN_REPS
    } else {
        ((BUDGET_S * 1e3 / t_ref).round() as usize).clamp(MIN_REPS, MAX_REPS)
    };
    let fwd = |f: &dyn Fn(&Tensor) -> Tensor| drop(f(&x));
    let (fwd_pairs, step_pairs) = if args.aten {
        (
            paired(
                reps,
                &mut || fwd(&reference),
                &mut [&mut || fwd(&native), &mut || fwd(&aten)],
            ),
            paired(
                reps,
                &mut || step(&reference),
                &mut [&mut || step(&native), &mut || step(&aten)],
            ),
        )
    } else {
        (
            paired(reps, &mut || fwd(&reference), &mut [&mut || fwd(&native)]),
            paired(reps, &mut || step(&reference), &mut [&mut || step(&native)]),
        )
    };
    let ref_peak = peak_mib(&mut || step(&reference));
    let mut impls = fwd_pairs.into_iter().zip(step_pairs);
    let mut make = |f: &dyn Fn(&Tensor) -> Tensor| -> Option<Impl> {
        let (forward, forward_backward) = impls.next()?;
        let peak = peak_mib(&mut || step(f));
        Some(Impl {
            forward,
            forward_backward,
            peak_mib: peak,
            peak_ratio: ratio(peak, ref_peak),
        })
    };
    let calibrated = make(&native).expect("native measured");
    let aten = if args.aten { make(&aten) } else { None };
    Ok(ShapeResult {
        batch: b,
        c_in,
        c_out,
        height: h,
        width: w,
        reps,
        conv2d_peak_mib: ref_peak,
        calibrated,
        aten,
    })
}

fn ratio(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    }
}

/// Offsets and sampling plans for every level
/// of the camera's depth-4 U-Net pyramid (3x3, stride 1, "same"), from scratch, best of three.
fn bench_pyramid(camera: &Camera) -> Result<PyramidResult> {
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
            .collect::<calibconv::Result<Vec<_>>>()?;
        let offsets_s = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let mut plan_bytes = 0;
        for off in &offsets {
            let plan = SamplingPlan::from_offsets(
                off,
                [1, 1],
                [1, 1],
                [1, 1],
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

/// A training step (forward in training mode, backward, SGD update) of the project's U-Net
/// ([`UNet`], batch norm, transposed up-sampling, 8-class segmentation head) with standard and
/// with calibrated 3x3 kernels, interleaved: base 32, depth 4, B2 at 256x256 (levels 256..16,
/// 32..512 channels); `--full`: the paper's classic U-Net (base 64, 64..1024 channels);
/// `--quick`: base 8, depth 3, B1 at 64x64.
fn bench_unet(camera: &Camera, args: &BenchArgs) -> Result<UnetResult> {
    let (batch, input, base, depth) = if args.quick {
        (1, [64, 64], 8, 3)
    } else if args.full {
        (2, [256, 256], 64, 4)
    } else {
        (2, [256, 256], 32, 4)
    };
    let config = UNetConfig {
        in_channels: 3,
        base,
        depth,
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
        let net = UNet::new(&vs.root(), &config, kind, input)?;
        let opt = nn::Sgd::default().build(&vs, 1e-3)?;
        nets.push((vs, net, opt));
    }
    let x = Tensor::randn([batch, 3, input[0], input[1]], (Kind::Float, Device::Cpu));
    let step = |i: usize, nets: &mut Vec<(nn::VarStore, UNet, nn::Optimizer)>| {
        let (_, net, opt) = &mut nets[i];
        let out = net.f_forward_t(&x, true).expect("U-Net forward");
        opt.backward_step(&out.square().mean(Kind::Float));
    };
    step(0, &mut nets);
    let t_ref = time_ms(&mut || step(0, &mut nets));
    let reps = if args.quick {
        MIN_REPS
    } else {
        ((2.0 * BUDGET_S * 1e3 / t_ref).round() as usize).clamp(MIN_REPS, MAX_REPS)
    };
    let nets = std::cell::RefCell::new(nets);
    let pairs = paired(
        reps,
        &mut || step(0, &mut nets.borrow_mut()),
        &mut [&mut || step(1, &mut nets.borrow_mut())],
    );
    let ref_peak = peak_mib(&mut || step(0, &mut nets.borrow_mut()));
    let cal_peak = peak_mib(&mut || step(1, &mut nets.borrow_mut()));
    let step = pairs.into_iter().next().expect("one candidate");
    let r = UnetResult {
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
        conv2d_peak_mib: ref_peak,
        calibrated_peak_mib: cal_peak,
        peak_ratio: ratio(cal_peak, ref_peak),
    };
    println!(
        "\nU-Net B{} 3x{}x{}, base {}, depth {}: training step conv2d {:.1} ms, calibrated {:.1} \
         ms ({:.2}x); peak {} vs {} MiB ({}x)",
        r.batch,
        r.input_hw[0],
        r.input_hw[1],
        r.base_channels,
        r.depth,
        r.step.reference_ms,
        r.step.candidate_ms,
        r.step.ratio,
        fmt_opt(r.conv2d_peak_mib, 0),
        fmt_opt(r.calibrated_peak_mib, 0),
        fmt_opt(r.peak_ratio, 2)
    );
    Ok(r)
}

/// CPU time of the process (all threads, user + system) in seconds, where the platform has it.
fn cpu_seconds() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        #[repr(C)]
        struct Timespec {
            sec: i64,
            nsec: i64,
        }
        extern "C" {
            fn clock_gettime(clock: std::ffi::c_int, ts: *mut Timespec) -> std::ffi::c_int;
        }
        const CLOCK_PROCESS_CPUTIME_ID: std::ffi::c_int = 2;
        let mut ts = Timespec { sec: 0, nsec: 0 };
        // SAFETY: clock_gettime writes one timespec (two 64-bit fields on 64-bit Linux) to `ts`.
        let rc = unsafe { clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
        (rc == 0).then_some(ts.sec as f64 + ts.nsec as f64 * 1e-9)
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// Reads a `kB` field of `/proc/self/status`.
fn status_kib(field: &str) -> Option<f64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    line[field.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Peak resident memory (MiB) that `f` adds: `VmHWM` after minus `VmRSS` before, with the
/// high-water mark reset first. `None` where `/proc` does not support it.
fn peak_mib(f: &mut dyn FnMut()) -> Option<f64> {
    std::fs::write("/proc/self/clear_refs", "5").ok()?;
    let before = status_kib("VmRSS:")?;
    f();
    let peak = status_kib("VmHWM:")?;
    Some((peak - before).max(0.0) / 1024.0)
}

/// Pins glibc's mmap threshold so large freed blocks are unmapped at once (see the module docs).
fn pin_malloc_threshold() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: std::ffi::c_int, value: std::ffi::c_int) -> std::ffi::c_int;
        }
        const M_MMAP_THRESHOLD: std::ffi::c_int = -3;
        // SAFETY: mallopt only changes allocator tuning; called before the benchmark allocates.
        unsafe {
            mallopt(M_MMAP_THRESHOLD, 256 * 1024);
        }
    }
}
