//! The benchmark behind `calibconv bench`: the calibrated convolution against `conv2d`,
//! interleaved in one process.
//!
//! Timings on a shared machine drift with the load, so every measurement is paired: within one
//! repetition the reference (`conv2d`, same weights) and the candidate run back to back (the
//! order alternates between repetitions), and the reported ratio is the median of the
//! per-repetition ratios, with a distribution-free 95% confidence interval of that median (order
//! statistics, `median_ci`). Times are medians too. `--presets` rows also carry the layer's
//! performance goal (`goal_limit`) and whether it holds, is contradicted or is inconclusive,
//! computed from the interval (`Outcome`), counted after the table. The system load
//! (`/proc/loadavg`) before and
//! after the timings is reported with them. Nothing here is asserted anywhere: these are numbers
//! for people.
//!
//! The timing process is configured like the trainer: the allocator is left alone (no `mallopt`),
//! and the thread count is libtorch's or `--threads`. Before the layer rows it runs one training
//! step of each U-Net it times (standard and calibrated, `measure::warm_like_trainer`), as a
//! trainer has before its later steps: glibc's dynamic mmap threshold then sits where a
//! trainer's does, and a row's `conv2d` no longer runs up to 4x faster or slower with what the
//! calibrated layer beside it frees (docs/bench/cpu-kernels.md). Peak
//! memory is measured afterwards in a child process (`calibconv bench ... --memory-child`, the
//! same arguments, which runs [`memory_child`]) that pins glibc's mmap threshold first
//! (`mallopt`), so freed tensors go back to the kernel instead of lingering
//! in the heap and hiding later allocations; pinned in the timing process it would make every
//! allocation over 256 KiB a fresh mmap with page faults, slowing `conv2d` and making the ratios
//! look better than in a training process. A measurement is `VmHWM` after one training
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
//! training. Its U-Net training steps are those of the two CPU profiles' networks: the quick
//! profile's tiny U-Net at 64x64 and the study profile's small one (depth 3) at 144x160, B8.
//!
//! Layout: this file holds the options and the report; `print` its printing; `paired` the paired
//! timing, its statistics and the goals; `measure` the timed and measured workloads; `proc` the
//! platform probes (`/proc`, `clock_gettime`, `mallopt`),
//! real on Linux only (elsewhere they report nothing). The CLI wrapper
//! (`src/commands/bench.rs`) parses flags, loads the camera and runs the memory child.

pub mod device;
mod measure;
mod paired;
mod print;
mod proc;

use std::path::PathBuf;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::Result;
use crate::kernel::pyramid_sizes;
use crate::nn::{Head, UNetConfig};
use crate::ops::{GemmLibrary, LargeWeights, NativeSetting, SmallKernelIsa};

pub use measure::memory_child;
use measure::{bench_functional, bench_pyramid, bench_shape, bench_unet, ratio, warm_like_trainer};
use paired::*;
use print::*;
use proc::{cpu_model, load_average};

/// A part of the benchmark.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    /// The table of layer shapes.
    Layers,
    /// Offsets and sampling plans of the camera's U-Net pyramid.
    Pyramid,
    /// The U-Net-shaped training step.
    Unet,
    /// The functional `ops::deform_conv2d` called again and again with one offsets tensor
    /// (B4, 32 channels, 128x128; its plan comes from the plan cache).
    Functional,
}

/// What to run (the flags of `calibconv bench`).
#[derive(Clone, Debug, Default)]
pub struct Options {
    /// A short run: fewer shapes and repetitions, no pyramid unless asked for.
    pub quick: bool,
    /// Every shape of the grid.
    pub full: bool,
    /// The layer shapes of the U-Net presets at the experiments' sizes.
    pub presets: bool,
    /// Also time the ATen backend.
    pub aten: bool,
    /// Skip the peak-memory pass.
    pub no_memory: bool,
    /// Explicit layer shapes `[batch, c_in, c_out, height, width]`.
    pub shapes: Vec<[i64; 5]>,
    /// The explicit shapes are first layers (no input gradient).
    pub first_layer: bool,
    /// Only these parts (empty: the default parts).
    pub only: Vec<Part>,
    /// The camera file, as named in the output.
    pub camera: PathBuf,
}

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
/// Repetitions of `--quick`.
const MIN_REPS: usize = 3;
/// Repetitions at least otherwise, so that a goal can hold or be contradicted: 15 give the
/// ratio's interval `x(4)` and `x(12)` ([`median_ci`]). (6, the fewest that give an interval at
/// all, made it the smallest and the largest of the six: the slow `classic` layers, which get
/// no more within `BUDGET_S`, came out inconclusive from one outlier, e.g. 128->128 at 128x128
/// forward 1.03x [1.01, 1.17].)
const CI_REPS: usize = 15;
/// Repetitions at most (a layer or U-Net step that fits `BUDGET_S` this many times gets them).
/// Each repetition is one call of each, alternating, as layers alternate in a training step;
/// millisecond layers need many to narrow the interval of their median ratio: at 15, the
/// earlier cap, single calls' page-fault bursts left intervals such as [1.21, 1.39] (32->16 at
/// 128x128 f+b). 101 gives about `x(41)`, `x(61)`. (Timing 10-50 calls back to back per
/// repetition instead narrowed them too, but moved medians: a layer called over and over keeps
/// its caches and allocator state, which it does not in a training step.)
const MAX_REPS: usize = 101;
/// Repetitions of the functional op's timing (each a forward+backward at B4, 128x128).
const FUNCTIONAL_REPS: usize = 15;

/// `--full`: every U-Net level at batch 1, 4 and 8.
fn full_shapes() -> Vec<Shape> {
    let levels = [(32, 256), (64, 128), (128, 64), (256, 32), (512, 16)];
    [1, 4, 8]
        .iter()
        .flat_map(|&b| levels.iter().map(move |&(c, s)| [b, c, c, s, s]))
        .collect()
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
    /// The layer's performance goal and its outcomes (presets only).
    goal: Option<Goal>,
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
    /// Which network: the profile it stands for (`--presets`) or the bench's default.
    network: &'static str,
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
pub struct Report {
    /// The CPU's name (`/proc/cpuinfo`), where known.
    cpu: Option<String>,
    threads: i32,
    /// The instruction-set level of the few-output-channel kernels (`ops::SmallKernelIsa`).
    small_kernels: String,
    /// The library of the large weights' products (`ops::LargeWeights`).
    large_weights: String,
    /// The library of the other float32 products (`ops::GemmLibrary`).
    gemm: String,
    /// `/proc/loadavg` (1, 5, 15 minutes) before and after the timings.
    load_before: Option<[f64; 3]>,
    load_after: Option<[f64; 3]>,
    note: &'static str,
    shapes: Vec<ShapeResult>,
    pyramid: Option<PyramidResult>,
    /// The U-Net training steps (`--presets`: the quick and the study profile's networks).
    unet: Vec<UnetResult>,
    /// `ops::deform_conv2d` with one offsets tensor, forward+backward against `conv2d`.
    functional: Option<Paired>,
}

/// What the memory child process (`--memory-child`) prints on its last line of stdout: peaks
/// (MiB) per layer, `[conv2d, calibrated, aten]`, and per U-Net step `[conv2d, calibrated]`.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct MemoryReport {
    layers: Vec<[Option<f64>; 3]>,
    unet: Vec<[Option<f64>; 2]>,
}

/// The layers the arguments select.
fn selected_layers(args: &Options) -> Result<Vec<Layer>> {
    let run_part = |p: Part| args.only.is_empty() || args.only.contains(&p);
    Ok(if !run_part(Part::Layers) {
        Vec::new()
    } else if args.presets {
        preset_layers()?
    } else if !args.shapes.is_empty() {
        let first = args.first_layer;
        args.shapes
            .iter()
            .map(|&shape| Layer {
                input_grad: !first,
                ..Layer::plain(shape)
            })
            .collect()
    } else if args.quick {
        QUICK.iter().copied().map(Layer::plain).collect()
    } else if args.full {
        full_shapes().into_iter().map(Layer::plain).collect()
    } else {
        DEFAULT.iter().copied().map(Layer::plain).collect()
    })
}

/// Runs the timings and prints them; then, unless `no_memory`, calls `memory_in_child` (which
/// runs [`memory_child`] in a fresh process with the same options and returns its report, or an
/// error to print) and prints the peak memory. Returns the report (the CLI writes it as JSON).
pub fn run(
    camera: &Camera,
    args: &Options,
    memory_in_child: impl FnOnce() -> std::result::Result<MemoryReport, String>,
) -> Result<Report> {
    tch::manual_seed(0);
    let layers = selected_layers(args)?;
    let run_part = |p: Part| args.only.is_empty() || args.only.contains(&p);
    let threads = tch::get_num_threads();
    let load_before = load_average();
    let small_kernels = format!("{:?}", SmallKernelIsa::current());
    let gemm = format!("{:?}", GemmLibrary::current());
    let large_weights = format!("{:?}", LargeWeights::current());
    let cpu = cpu_model();
    println!(
        "calibconv bench: {}, {threads} libtorch threads, camera {}, load {}, few-output-channel \
         kernels {small_kernels} (large weights' products: {large_weights}), other products \
         {gemm}; ratios are calibrated / conv2d (medians \
         of paired, interleaved runs)",
        cpu.as_deref().unwrap_or("CPU unknown"),
        args.camera.display(),
        fmt_load(load_before)
    );
    // (the functional loop too: without it, its buffers came from a fresh process's allocator,
    // and its ratio was 1.3x or 2.0x from one process to the next at the same main)
    let functional_asked = args.only.contains(&Part::Functional);
    if !layers.is_empty() || functional_asked {
        warm_like_trainer(camera, args)?;
    }
    if !layers.is_empty() {
        print_header(args.aten);
    }
    let mut results = Vec::new();
    for layer in &layers {
        let r = bench_shape(camera, layer, args)?;
        print_row(&r);
        results.push(r);
    }
    print_goals(&results);
    // The full-resolution pyramid takes seconds: not part of --quick unless asked for.
    let pyramid = if run_part(Part::Pyramid) && !(args.quick && args.only.is_empty()) {
        Some(bench_pyramid(camera)?)
    } else {
        None
    };
    let mut unet = if run_part(Part::Unet) {
        bench_unet(camera, args)?
    } else {
        Vec::new()
    };
    // Part of the default run only when asked for (it repeats a layer of the table).
    let functional = if functional_asked {
        Some(bench_functional(camera, args)?)
    } else {
        None
    };
    let load_after = load_average();
    println!("\nload after the timings: {}", fmt_load(load_after));
    if !args.no_memory && (!results.is_empty() || !unet.is_empty()) {
        match memory_in_child() {
            Ok(mem) => {
                merge_memory(&mut results, &mut unet, &mem);
                print_memory(&results, &unet);
            }
            Err(e) => println!(
                "
peak memory not measured: {e}"
            ),
        }
    }
    Ok(Report {
        cpu,
        threads,
        small_kernels,
        large_weights,
        gemm,
        load_before,
        load_after,
        note: "ratios = medians of per-repetition (calibrated / conv2d) times, interleaved, in a \
               process configured like the trainer; peak = VmHWM - VmRSS around one training \
               step, measured in a separate process with glibc's mmap threshold pinned",
        shapes: results,
        pyramid,
        unet,
        functional,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `P(Binomial(n, 1/2) <= k)` from exact integer counts (an oracle independent of the
    /// running product in `median_ci`).
    fn binomial_cdf(n: u32, k: u32) -> f64 {
        let choose =
            |n: u32, r: u32| (0..r).fold(1u128, |c, i| c * u128::from(n - i) / u128::from(i + 1));
        let below: u128 = (0..=k).map(|r| choose(n, r)).sum();
        below as f64 / 2f64.powi(n as i32)
    }

    /// The interval of the median is the widest symmetric pair of order statistics whose
    /// binomial tails are each at most 2.5% (coverage >= 95%), the next narrower pair not;
    /// none below 6 values.
    #[test]
    fn median_interval_is_the_binomial_order_statistic_pair() {
        for n in 1..=60usize {
            let sorted: Vec<f64> = (1..=n).map(|i| i as f64).collect();
            let ci = median_ci(&sorted);
            if n < 6 {
                assert_eq!(ci, None, "n = {n}");
                continue;
            }
            let [lo, hi] = ci.unwrap_or_else(|| panic!("n = {n}: no interval"));
            let j = lo as usize; // x(j) = j here
            assert_eq!(hi as usize, n + 1 - j, "n = {n}: symmetric");
            let tail = binomial_cdf(n as u32, j as u32 - 1);
            assert!(tail <= 0.025, "n = {n}, j = {j}: tail {tail}");
            assert!(1.0 - 2.0 * tail >= 0.95, "n = {n}: coverage");
            assert!(
                binomial_cdf(n as u32, j as u32) > 0.025,
                "n = {n}: j = {j} is not the largest"
            );
        }
        // 15 repetitions: x(4) and x(12).
        let fifteen: Vec<f64> = (1..=15).map(f64::from).collect();
        assert_eq!(median_ci(&fifteen), Some([4.0, 12.0]));
        // MAX_REPS (101): x(41) and x(61). (median_ci's running product rounds there, the
        // binomial coefficients being beyond f64's exact integers, but P(X <= 40) = 2.30% and
        // P(X <= 41) = 3.64% lie far from the 2.5% boundary.)
        let most: Vec<f64> = (1..=MAX_REPS).map(|i| i as f64).collect();
        assert_eq!(median_ci(&most), Some([41.0, 61.0]));
    }

    #[test]
    fn goals_follow_the_presets_and_channel_counts() {
        assert_eq!(goal_limit("tiny", 3, 8), Some(1.3));
        assert_eq!(goal_limit("small", 64, 32), Some(1.3));
        assert_eq!(goal_limit("small", 64, 128), Some(1.15));
        assert_eq!(goal_limit("classic", 64, 64), Some(1.15));
        assert_eq!(goal_limit("classic", 3, 64), None);
        assert_eq!(goal_limit("classic", 128, 32), None);
        assert_eq!(goal_limit("", 256, 256), None);
    }

    /// A goal holds only when the whole interval is within it, is contradicted only when the
    /// whole interval is above it, and is inconclusive without an interval.
    #[test]
    fn goal_outcomes_come_from_the_interval() {
        assert_eq!(Outcome::of(Some([1.1, 1.3]), 1.3), Outcome::Holds);
        assert_eq!(Outcome::of(Some([1.1, 1.31]), 1.3), Outcome::Inconclusive);
        assert_eq!(Outcome::of(Some([1.3, 1.4]), 1.3), Outcome::Inconclusive);
        assert_eq!(Outcome::of(Some([1.31, 1.4]), 1.3), Outcome::Contradicted);
        assert_eq!(Outcome::of(None, 1.3), Outcome::Inconclusive);
    }

    /// `--shape` layers need the input gradient unless `--first-layer` says they read the image;
    /// the presets mark their first layers themselves.
    #[test]
    fn explicit_shapes_are_first_layers_only_when_asked() {
        let shape = [8, 3, 16, 128, 128];
        for first_layer in [false, true] {
            let opts = Options {
                shapes: vec![shape, [2, 16, 16, 32, 32]],
                first_layer,
                ..Default::default()
            };
            let layers = selected_layers(&opts).unwrap();
            assert_eq!(layers.len(), 2);
            assert_eq!(layers[0].shape, shape);
            assert!(layers.iter().all(|l| l.input_grad != first_layer));
        }
        let presets = selected_layers(&Options {
            presets: true,
            ..Default::default()
        })
        .unwrap();
        assert!(presets.iter().any(|l| !l.input_grad && l.shape[1] == 3));
        assert!(presets
            .iter()
            .filter(|l| l.shape[1] > 3)
            .all(|l| l.input_grad));
    }

    /// `--presets` times the training step of the networks the quick and the study profiles
    /// fine-tune, at their batch size and input width: the bench follows the profiles.
    #[test]
    fn preset_unet_steps_are_the_profiles_networks() {
        use crate::experiment::profile::Profile;
        let specs = measure::unet_specs(&Options {
            presets: true,
            ..Default::default()
        });
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        for (name, label) in [
            ("quick", "quick profile: tiny"),
            ("study", "study profile: small, depth 3"),
        ] {
            let file = root.join(format!("experiments/paper/profiles/{name}.toml"));
            let profile = Profile::load(&file).unwrap();
            let all = &profile.all;
            let model = all["model"].as_table().unwrap();
            let preset = model["preset"].as_str().unwrap();
            let cfg = UNetConfig::preset(preset, Head::Depth).unwrap();
            let depth = model
                .get("depth")
                .map_or(cfg.depth, |d| d.as_integer().unwrap() as usize);
            let width = all["input"]["width"].as_integer().unwrap();
            let batch = all["train"]["batch_size"].as_integer().unwrap();
            let spec = specs.iter().find(|s| s.label == label).unwrap();
            assert_eq!(
                (spec.base, spec.depth, spec.input[1], spec.batch),
                (cfg.base, depth, width, batch),
                "{name}"
            );
            assert_eq!(
                spec.input[0] % (1 << depth),
                0,
                "{name}: a height the U-Net takes"
            );
        }
    }
}
