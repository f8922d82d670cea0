//! `calibconv bench`: the calibrated convolution against `conv2d`, interleaved in one process.
//!
//! Timings on a shared machine drift with the load, so every measurement is paired: within one
//! repetition the reference (`conv2d`, same weights) and the candidate run back to back (the
//! order alternates between repetitions), and the reported ratio is the median of the
//! per-repetition ratios. Times are medians too. The system load (`/proc/loadavg`) before and
//! after the timings is reported with them. Nothing here is asserted anywhere: these are numbers
//! for people.
//!
//! The timing process is configured like the trainer: the allocator is left alone (no `mallopt`),
//! and the thread count is libtorch's or `--threads`. Peak memory is measured afterwards in a
//! child process (`calibconv bench ... --memory-child`, the same arguments) that pins glibc's
//! mmap threshold first (`mallopt`), so freed tensors go back to the kernel instead of lingering
//! in the heap and hiding later allocations; pinning it in the timing process made every
//! allocation over 256 KiB a fresh mmap with page faults, which slowed `conv2d` 1.5-3.5x and made
//! the ratios look better than in a training process. A measurement is `VmHWM` after one training
//! step minus `VmRSS` before it (the kernel's high-water mark, reset by writing `5` to
//! `/proc/self/clear_refs`), i.e. the resident memory the step added at its peak (inputs, weights
//! and the probe are allocated before and not counted). Limits: page granularity, process-wide
//! (any thread's memory counts), and memory the allocator keeps cached from earlier steps is not
//! seen again.
//!
//! `--presets` times every 3x3 layer shape of the project's U-Net presets at the sizes the
//! experiments use them (tiny at 64x64 and small at 128x128, batch 8; classic at 256x256, batch
//! 2, a CPU-sized stand-in for the paper's 1088x960 GPU runs). A network's first layer reads the
//! image, which needs no gradient: its forward+backward computes the weight gradient only, as in
//! training.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

use calibconv::camera::{Camera, CameraModel};
use calibconv::io::write_bytes_atomic;
use calibconv::kernel::{compute_offsets, pyramid_sizes, InputFrame, LayerGeometry};
use calibconv::nn::{CalibratedConv2d, Conv2dConfig, ConvKind, Head, UNet, UNetConfig, UpMode};
use calibconv::ops::{deform_conv2d, deform_conv2d_planned_with, Backend, Border, SamplingPlan};

use super::load_camera;
use crate::cli::{BenchArgs, BenchPart};

/// One layer shape: `[batch, c_in, c_out, height, width]` (3x3, stride 1, "same" padding).
type Shape = [i64; 5];

/// A layer to time: a shape, whether the input needs a gradient (not for a network's first
/// layer, which reads the image), and where it comes from.
#[derive(Clone, Debug)]
struct Layer {
    shape: Shape,
    input_grad: bool,
    /// The preset it belongs to ("" for explicit shapes).
    net: &'static str,
    /// How many layers of the preset have this shape.
    count: usize,
}

impl Layer {
    fn plain(shape: Shape) -> Self {
        Layer {
            shape,
            input_grad: true,
            net: "",
            count: 1,
        }
    }
}

/// The presets of `--presets`: (preset, input side, batch).
const PRESET_SIZES: &[(&str, i64, i64)] =
    &[("tiny", 64, 8), ("small", 128, 8), ("classic", 256, 2)];

/// Every 3x3 layer of the presets' U-Nets (transposed up-sampling, as `nn::unet` builds them):
/// `inc` (in -> base -> base), `down l` (w(l-1) -> w(l) -> w(l)) and `up` to level l
/// (2 w(l) -> w(l) -> w(l)), w(l) = base * 2^l, at the pyramid sizes; identical shapes merged
/// with a count.
fn preset_layers() -> Result<Vec<Layer>> {
    let mut layers: Vec<Layer> = Vec::new();
    for &(name, side, batch) in PRESET_SIZES {
        let cfg = UNetConfig::preset(name, Head::Depth)?;
        let sizes = pyramid_sizes([side as usize, side as usize], cfg.depth);
        let w = |l: usize| cfg.base << l;
        let mut add = |c_in: i64, c_out: i64, l: usize| {
            let [h, wd] = sizes[l].map(|v| v as i64);
            let shape = [batch, c_in, c_out, h, wd];
            let input_grad = !(l == 0 && c_in == cfg.in_channels);
            match layers
                .iter_mut()
                .find(|x| x.net == name && x.shape == shape && x.input_grad == input_grad)
            {
                Some(x) => x.count += 1,
                None => layers.push(Layer {
                    shape,
                    input_grad,
                    net: name,
                    count: 1,
                }),
            }
        };
        add(cfg.in_channels, w(0), 0);
        add(w(0), w(0), 0);
        for l in 1..=cfg.depth {
            add(w(l - 1), w(l), l);
            add(w(l), w(l), l);
        }
        for l in (0..cfg.depth).rev() {
            add(2 * w(l), w(l), l);
            add(w(l), w(l), l);
        }
    }
    Ok(layers)
}

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
    /// The same from the process's CPU time (all threads, user + system) instead of wall time:
    /// on a machine loaded beyond its cores a run longer than a scheduler time slice is
    /// preempted more often than a short one, which inflates wall-time ratios; with one thread
    /// the CPU-time ratio is the work ratio (with more, it counts OpenMP's spinning too).
    cpu_ratio: Option<f64>,
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
    /// The preset the layer belongs to ("" for explicit shapes) and how many of its layers have
    /// this shape.
    net: &'static str,
    count: usize,
    batch: i64,
    c_in: i64,
    c_out: i64,
    height: i64,
    width: i64,
    /// Whether forward+backward computes the input gradient (not for a first layer).
    input_grad: bool,
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
    /// `/proc/loadavg` (1, 5, 15 minutes) before and after the timings.
    load_before: Option<[f64; 3]>,
    load_after: Option<[f64; 3]>,
    note: &'static str,
    shapes: Vec<ShapeResult>,
    pyramid: Option<PyramidResult>,
    unet: Option<UnetResult>,
    /// `ops::deform_conv2d` with one offsets tensor, forward+backward against `conv2d`.
    functional: Option<Paired>,
}

/// What the memory child process (`--memory-child`) prints on its last line of stdout: peaks
/// (MiB) per layer, `[conv2d, calibrated, aten]`, and of the U-Net step `[conv2d, calibrated]`.
#[derive(Debug, Default, Serialize, Deserialize)]
struct MemoryReport {
    layers: Vec<[Option<f64>; 3]>,
    unet: Option<[Option<f64>; 2]>,
}

/// The layers the arguments select.
fn selected_layers(args: &BenchArgs) -> Result<Vec<Layer>> {
    let run_part = |p: BenchPart| args.only.is_empty() || args.only.contains(&p);
    Ok(if !run_part(BenchPart::Layers) {
        Vec::new()
    } else if args.presets {
        preset_layers()?
    } else if !args.shapes.is_empty() {
        args.shapes.iter().copied().map(Layer::plain).collect()
    } else if args.quick {
        QUICK.iter().copied().map(Layer::plain).collect()
    } else if args.full {
        full_shapes().into_iter().map(Layer::plain).collect()
    } else {
        DEFAULT.iter().copied().map(Layer::plain).collect()
    })
}

pub fn run(args: BenchArgs) -> Result<()> {
    if [args.quick, args.full, args.presets]
        .iter()
        .filter(|&&v| v)
        .count()
        > 1
    {
        bail!("--quick, --full and --presets exclude each other");
    }
    if let Some(n) = args.threads {
        if n < 1 {
            bail!("--threads must be >= 1");
        }
        tch::set_num_threads(n);
    }
    tch::manual_seed(0);
    let camera = load_camera(&args.camera)?;
    let layers = selected_layers(&args)?;
    let run_part = |p: BenchPart| args.only.is_empty() || args.only.contains(&p);
    if args.memory_child {
        return memory_child(&camera, &layers, run_part(BenchPart::Unet), &args);
    }
    let threads = tch::get_num_threads();
    let load_before = load_average();
    println!(
        "calibconv bench: {threads} libtorch threads, camera {}, load {}; ratios are calibrated \
         / conv2d (medians of paired, interleaved runs)",
        args.camera.display(),
        fmt_load(load_before)
    );
    if !layers.is_empty() {
        print_header(args.aten);
    }
    let mut results = Vec::new();
    for layer in &layers {
        let r = bench_shape(&camera, layer, &args)?;
        print_row(&r);
        results.push(r);
    }
    // The full-resolution pyramid takes seconds: not part of --quick unless asked for.
    let pyramid = if run_part(BenchPart::Pyramid) && !(args.quick && args.only.is_empty()) {
        Some(bench_pyramid(&camera)?)
    } else {
        None
    };
    let mut unet = if run_part(BenchPart::Unet) {
        Some(bench_unet(&camera, &args)?)
    } else {
        None
    };
    // Part of the default run only when asked for (it repeats a layer of the table).
    let functional = if args.only.contains(&BenchPart::Functional) {
        Some(bench_functional(&camera, &args)?)
    } else {
        None
    };
    let load_after = load_average();
    println!("\nload after the timings: {}", fmt_load(load_after));
    if !args.no_memory && (!results.is_empty() || unet.is_some()) {
        match memory_in_child() {
            Ok(mem) => {
                merge_memory(&mut results, unet.as_mut(), &mem);
                print_memory(&results, unet.as_ref());
            }
            Err(e) => println!(
                "
peak memory not measured: {e:#}"
            ),
        }
    }
    let report = Report {
        threads,
        load_before,
        load_after,
        note: "ratios = medians of per-repetition (calibrated / conv2d) times, interleaved, in a \
               process configured like the trainer; peak = VmHWM - VmRSS around one training \
               step, measured in a separate process with glibc's mmap threshold pinned",
        shapes: results,
        pyramid,
        unet,
        functional,
    };
    if let Some(path) = &args.json {
        write_json(path, &report)?;
        println!("\nwrote {}", path.display());
    }
    Ok(())
}

/// `/proc/loadavg`'s three load averages, where the platform has them.
fn load_average() -> Option<[f64; 3]> {
    let text = std::fs::read_to_string("/proc/loadavg").ok()?;
    let v: Vec<f64> = text
        .split_whitespace()
        .take(3)
        .map(|x| x.parse().ok())
        .collect::<Option<_>>()?;
    v.try_into().ok()
}

fn fmt_load(l: Option<[f64; 3]>) -> String {
    l.map_or("-".into(), |l| {
        format!("{:.2} {:.2} {:.2}", l[0], l[1], l[2])
    })
}

/// Runs this benchmark again, with the same arguments and `--memory-child`, and reads its
/// [`MemoryReport`].
fn memory_in_child() -> Result<MemoryReport> {
    let exe = std::env::current_exe().context("cannot find the calibconv executable")?;
    let out = std::process::Command::new(&exe)
        .args(std::env::args_os().skip(1))
        .arg("--memory-child")
        .stderr(std::process::Stdio::inherit())
        .output()
        .with_context(|| format!("cannot run {}", exe.display()))?;
    if !out.status.success() {
        bail!("the memory process failed ({})", out.status);
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let last = text.lines().last().unwrap_or_default();
    serde_json::from_str(last).context("the memory process printed no report")
}

fn merge_memory(results: &mut [ShapeResult], unet: Option<&mut UnetResult>, mem: &MemoryReport) {
    for (r, m) in results.iter_mut().zip(&mem.layers) {
        r.conv2d_peak_mib = m[0];
        r.calibrated.peak_mib = m[1];
        r.calibrated.peak_ratio = ratio(m[1], m[0]);
        if let Some(a) = r.aten.as_mut() {
            a.peak_mib = m[2];
            a.peak_ratio = ratio(m[2], m[0]);
        }
    }
    if let (Some(u), Some(m)) = (unet, mem.unet) {
        u.conv2d_peak_mib = m[0];
        u.calibrated_peak_mib = m[1];
        u.peak_ratio = ratio(m[1], m[0]);
    }
}

fn print_memory(results: &[ShapeResult], unet: Option<&UnetResult>) {
    if !results.is_empty() {
        println!("\npeak memory of one training step (separate process, mmap threshold pinned):");
        println!(
            "{:>7} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5}",
            "net", "B", "Cin", "Cout", "HxW", "conv MiB", "cal MiB", "x"
        );
    }
    for r in results {
        println!(
            "{:>7} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5}",
            r.net,
            r.batch,
            r.c_in,
            r.c_out,
            format!("{}x{}", r.height, r.width),
            fmt_opt(r.conv2d_peak_mib, 1),
            fmt_opt(r.calibrated.peak_mib, 1),
            fmt_opt(r.calibrated.peak_ratio, 2),
        );
    }
    if let Some(u) = unet {
        println!(
            "U-Net step peak: conv2d {} MiB, calibrated {} MiB ({}x)",
            fmt_opt(u.conv2d_peak_mib, 0),
            fmt_opt(u.calibrated_peak_mib, 0),
            fmt_opt(u.peak_ratio, 2)
        );
    }
}

/// The memory pass (`--memory-child`): pins the allocator, measures one training step per layer
/// (and of the U-Net), prints a [`MemoryReport`] as the last line of stdout. No timings.
fn memory_child(camera: &Camera, layers: &[Layer], unet: bool, args: &BenchArgs) -> Result<()> {
    pin_malloc_threshold();
    let mut report = MemoryReport::default();
    for layer in layers {
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
        let mut nets = UnetBench::new(camera, args)?;
        nets.step(0);
        let r = peak_mib(&mut || nets.step(0));
        nets.step(1);
        let c = peak_mib(&mut || nets.step(1));
        report.unet = Some([r, c]);
    }
    println!("{}", serde_json::to_string(&report)?);
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
        "\n{:>7} {:>2} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5} {:>5} | {:>8} {:>8} {:>5} {:>5}{}",
        "net",
        "n",
        "B",
        "Cin",
        "Cout",
        "HxW",
        "conv fwd",
        "cal fwd",
        "x",
        "cpu x",
        "conv f+b",
        "cal f+b",
        "x",
        "cpu x",
        if aten { " | aten fwd x  f+b x" } else { "" }
    );
}

fn print_row(r: &ShapeResult) {
    let c = &r.calibrated;
    let mut line =
        format!(
        "{:>7} {:>2} {:>2} {:>4} {:>4} {:>8} | {:>8.2} {:>8.2} {:>5.2} {:>5} | {:>8.2} {:>8.2} {:>5.2} {:>5}",
        r.net,
        r.count,
        r.batch,
        r.c_in,
        r.c_out,
        format!("{}x{}{}", r.height, r.width, if r.input_grad { "" } else { "*" }),
        c.forward.reference_ms,
        c.forward.candidate_ms,
        c.forward.ratio,
        fmt_opt(c.forward.cpu_ratio, 2),
        c.forward_backward.reference_ms,
        c.forward_backward.candidate_ms,
        c.forward_backward.ratio,
        fmt_opt(c.forward_backward.cpu_ratio, 2),
    );
    if let Some(a) = &r.aten {
        line.push_str(&format!(
            " | {:>10.2} {:>6.2}",
            a.forward.ratio, a.forward_backward.ratio
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

/// Wall and process CPU time of `f` in milliseconds.
fn time_both_ms(f: &mut dyn FnMut()) -> (f64, Option<f64>) {
    let cpu0 = cpu_seconds();
    let wall = time_ms(f);
    let cpu = cpu_seconds().zip(cpu0).map(|(b, a)| (b - a) * 1e3);
    (wall, cpu)
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
    let mut times = vec![Vec::with_capacity(reps); n + 1]; // slot 0: the reference
    for rep in 0..reps {
        // Rotate who goes first.
        for k in 0..=n {
            let slot = (k + rep) % (n + 1);
            let t = if slot == 0 {
                time_both_ms(reference)
            } else {
                time_both_ms(candidates[slot - 1])
            };
            times[slot].push(t);
        }
    }
    let wall = |v: &[(f64, Option<f64>)]| v.iter().map(|t| t.0).collect::<Vec<_>>();
    let ref_wall = wall(&times[0]);
    times[1..]
        .iter()
        .map(|c| {
            let cpu: Option<Vec<f64>> = c
                .iter()
                .zip(&times[0])
                .map(|(c, r)| Some(c.1? / r.1?.max(1e-6)))
                .collect();
            Paired {
                reference_ms: median(ref_wall.clone()),
                candidate_ms: median(wall(c)),
                ratio: median(c.iter().zip(&ref_wall).map(|(c, r)| c.0 / r).collect()),
                cpu_ratio: cpu.map(median),
            }
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
            camera,
            &InputFrame::default(),
            [h, w],
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

fn bench_shape(camera: &Camera, layer: &Layer, args: &BenchArgs) -> Result<ShapeResult> {
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
        ((BUDGET_S * 1e3 / t_ref).round() as usize).clamp(MIN_REPS, MAX_REPS)
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
/// with calibrated 3x3 kernels: base 32, depth 4, B2 at 256x256 (levels 256..16, 32..512
/// channels); `--full`: the paper's classic U-Net (base 64, 64..1024 channels); `--presets`:
/// the quick profile's tiny U-Net (base 8, depth 3) at B8, 64x64; `--quick`: the tiny one at B1.
struct UnetBench {
    nets: Vec<(nn::VarStore, UNet, nn::Optimizer)>,
    x: Tensor,
    batch: i64,
    input: [i64; 2],
    base: i64,
    depth: usize,
}

impl UnetBench {
    fn new(camera: &Camera, args: &BenchArgs) -> Result<Self> {
        let (batch, input, base, depth) = if args.quick {
            (1, [64, 64], 8, 3)
        } else if args.presets {
            (8, [64, 64], 8, 3)
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
        Ok(UnetBench {
            nets,
            x,
            batch,
            input,
            base,
            depth,
        })
    }

    /// One training step of net 0 (standard) or 1 (calibrated).
    fn step(&mut self, i: usize) {
        let (_, net, opt) = &mut self.nets[i];
        let out = net.f_forward_t(&self.x, true).expect("U-Net forward");
        opt.backward_step(&out.square().mean(Kind::Float));
    }
}

fn bench_unet(camera: &Camera, args: &BenchArgs) -> Result<UnetResult> {
    let mut nets = UnetBench::new(camera, args)?;
    nets.step(0);
    nets.step(1);
    let t_ref = time_ms(&mut || nets.step(0));
    let reps = if args.quick {
        MIN_REPS
    } else {
        ((2.0 * BUDGET_S * 1e3 / t_ref).round() as usize).clamp(MIN_REPS, MAX_REPS)
    };
    let (batch, input, base, depth) = (nets.batch, nets.input, nets.base, nets.depth);
    let nets = std::cell::RefCell::new(nets);
    let pairs = paired(
        reps,
        &mut || nets.borrow_mut().step(0),
        &mut [&mut || nets.borrow_mut().step(1)],
    );
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
        conv2d_peak_mib: None,
        calibrated_peak_mib: None,
        peak_ratio: None,
    };
    println!(
        "\nU-Net B{} 3x{}x{}, base {}, depth {}: training step conv2d {:.1} ms, calibrated {:.1} \
         ms ({:.2}x; CPU time {}x)",
        r.batch,
        r.input_hw[0],
        r.input_hw[1],
        r.base_channels,
        r.depth,
        r.step.reference_ms,
        r.step.candidate_ms,
        r.step.ratio,
        fmt_opt(r.step.cpu_ratio, 2),
    );
    Ok(r)
}

/// The functional op as a researcher's own loop calls it: `ops::deform_conv2d` with the same
/// offsets tensor every step (F195 offsets, B4, 32 -> 32, 128x128), forward+backward against
/// `conv2d` with the same weights. The plan is built on the first call and then taken from the
/// plan cache.
fn bench_functional(camera: &Camera, args: &BenchArgs) -> Result<Paired> {
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
    let reps = if args.quick { MIN_REPS } else { MAX_REPS };
    let p = paired(reps, &mut || reference(), &mut [&mut || functional()])
        .pop()
        .expect("one candidate");
    println!(
        "\nfunctional ops::deform_conv2d, one offsets tensor, B{b} {c}->{c} {h}x{w}: \
         forward+backward conv2d {:.1} ms, deform_conv2d {:.1} ms ({:.2}x; CPU time {}x)",
        p.reference_ms,
        p.candidate_ms,
        p.ratio,
        fmt_opt(p.cpu_ratio, 2)
    );
    Ok(p)
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
