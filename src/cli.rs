//! Command-line interface (clap derive; the doc comments are the help text).

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

use calibconv::camera::import::{Format, OpenCvModel};
use calibconv::camera::PixelConvention;

/// Calibrated convolutions for fisheye cameras: kernel offsets from a camera calibration, and
/// the deformable convolution that uses them.
#[derive(Debug, Parser)]
#[command(name = "calibconv", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Compute the calibrated offsets of one layer and write them as safetensors (tensor
    /// `offsets`, layout [2*k*k, H_out, W_out], per tap the pair (dy, dx), as torchvision).
    Offsets(OffsetsArgs),
    /// Draw a grid of calibrated kernels over an image (or a blank image circle) as a PNG.
    Kernels(KernelsArgs),
    /// The main job: offsets for the whole U-Net pyramid of a camera (timed), the kernel figure,
    /// and a calibrated convolution run forward and backward, written to --out.
    Demo(DemoArgs),
    /// Benchmark the calibrated convolution against conv2d (interleaved, in a process configured
    /// like the trainer): time and ratio per layer shape (`--presets`: every layer of the U-Net
    /// presets), offsets + plans for the camera's U-Net pyramid, and a U-Net training step; peak
    /// memory afterwards in a second process.
    Bench(BenchArgs),
    /// Benchmark on a device (the GPU check): the calibrated layers of U-Net presets against
    /// `conv2d` (cuDNN on CUDA) and U-Net training steps standard against calibrated,
    /// synchronised, interleaved, medians with 95% intervals of the ratios; peak memory per
    /// step in child processes.
    BenchDevice(BenchDeviceArgs),
    /// Camera files: import a calibration from another tool.
    Camera(CameraArgs),
    /// Write data sets of fisheye / perspective / rectified views (RGB, depth, labels, mask)
    /// rendered from panoramas, procedural or Stanford 2D-3D-S, as a config describes
    /// (default: the embedded data/synth.toml); deterministic and resumable.
    Synth(crate::commands::synth::SynthArgs),
    /// Train the U-Net an experiment file describes, then run its evaluations (run directory:
    /// OUTPUT/NAME with checkpoints, CSV logs, TensorBoard events and evaluation results).
    Train(TrainArgs),
    /// Evaluate an experiment's checkpoint (default: its best) with its [[eval]] entries.
    Eval(EvalArgs),
    /// Convert a PyTorch checkpoint (.pth / .pt, e.g. milesial/Pytorch-UNet) to safetensors +
    /// JSON sidecar, usable as an experiment's initial weights (needs the .venv of make setup).
    Convert(crate::commands::convert::ConvertArgs),
    /// Write a calibconv checkpoint as a PyTorch state_dict (safetensors, milesial/Pytorch-UNet
    /// names) that UNet.load_state_dict(..., strict=True) accepts.
    Export(crate::commands::export::ExportArgs),
    /// Run every experiment of a folder (e.g. experiments/paper) with a profile, in dependency
    /// order (fine-tunings after their baseline): complete runs are skipped, interrupted ones
    /// resumed, failures reported at the end (exit status 1) without stopping the others. On
    /// SIGUSR1, SIGTERM or SIGINT the runs in progress finish their step, write their checkpoint
    /// and the sweep exits with status 75 (the next sweep resumes them).
    Sweep(SweepArgs),
    /// What this build runs on: libtorch (version, folder), tch, whether libtorch's CUDA backend
    /// is linked, CUDA devices, cuDNN, the native CPU kernels and threads.
    Info(InfoArgs),
    /// Tables (Markdown, CSV), radial plots, qualitative grids, a point cloud and REPORT.md from
    /// the run directories of a sweep's output folder (e.g. results/quick).
    Report(ReportArgs),
}

#[derive(Debug, Args)]
pub struct BenchDeviceArgs {
    /// `cpu`, `cuda` or `cuda:N`.
    #[arg(long, default_value = "cuda")]
    pub device: String,
    /// Camera whose calibrated offsets the layers use.
    #[arg(long, default_value = "data/cameras/f195.toml")]
    pub camera: PathBuf,
    /// Time every distinct 3x3 layer of a U-Net preset at an input size and batch,
    /// `PRESET:HxW:B` (e.g. `classic:1088x960:8`, the paper's). Repeatable.
    #[arg(long = "layers", value_name = "PRESET:HxW:B")]
    pub layers: Vec<String>,
    /// Time training steps of a U-Net preset, standard against calibrated, `PRESET:HxW:B`.
    /// Repeatable.
    #[arg(long = "step", value_name = "PRESET:HxW:B")]
    pub steps: Vec<String>,
    /// Paired repetitions per row.
    #[arg(long, default_value_t = 15)]
    pub reps: usize,
    /// Skip the peak-memory children of the steps.
    #[arg(long)]
    pub no_memory: bool,
    /// Write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Internal: the memory child, `KERNEL` standard or calibrated, for the one `--step`.
    #[arg(long, hide = true, value_name = "KERNEL")]
    pub memory_child: Option<String>,
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// Print JSON (one object) instead of lines.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct SweepArgs {
    /// Folder of experiment files (*.toml; profiles in its profiles/ subfolder).
    pub dir: PathBuf,
    /// Profile: NAME for DIR/profiles/NAME.toml (quick, paper), or a file.
    #[arg(long)]
    pub profile: Option<String>,
    /// Run only experiments matching PATTERN (`*` globs; without `*`: names containing it; an
    /// exact name: that run only). Repeatable.
    #[arg(long = "only", value_name = "PATTERN")]
    pub only: Vec<String>,
    /// Runs at a time within a dependency level.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// libtorch CPU threads per process (default: libtorch's choice). On a shared or small
    /// machine, `--jobs 2 --threads 1` is much faster than one run on 2 threads: busy-waiting
    /// OpenMP threads collapse when the cores are oversubscribed.
    #[arg(long)]
    pub threads: Option<i32>,
    /// Override a key of every experiment after the profile (`optimizer.lr=1e-4`,
    /// `train.steps=10`); recorded in each run's sweep.json. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Replicates: run the whole sweep once per seed, run directories OUTPUT/seed-S/NAME
    /// (overrides the profile's `seeds`). `--seeds 0,1,2`.
    #[arg(long, value_name = "S,S,...", value_delimiter = ',')]
    pub seeds: Option<Vec<u64>>,
    /// Of the seeds, run only this one (repeatable): what a SLURM array task runs.
    #[arg(long, value_name = "S")]
    pub only_seed: Vec<u64>,
    /// Write SLURM scripts (one job array per dependency level, chained with
    /// --dependency=afterok; one task per run and seed; resources from the profile's [slurm])
    /// to DIR instead of running.
    #[arg(long, value_name = "DIR")]
    pub emit_slurm: Option<PathBuf>,
    /// Override a key of the profile's [slurm] table for --emit-slurm (`gres=gpu:2`,
    /// `time=02:00:00`, `extra=--qos=long` adds a line). Repeatable.
    #[arg(long = "slurm-set", value_name = "KEY=VALUE")]
    pub slurm_set: Vec<String>,
    /// List the plan (level, state) and stop.
    #[arg(long)]
    pub dry_run: bool,
    /// Print where each run stands and stop: complete, running (PID or SLURM job and task),
    /// interrupted at step N, failed (the error's first line) or not started, with the steps
    /// done and the last checkpoint's time. Reads the run directories' records only (safe
    /// while the runs train, here or on SLURM nodes); give the same profile, --set and
    /// --seeds as the sweep.
    #[arg(long, conflicts_with_all = ["dry_run", "emit_slurm"])]
    pub status: bool,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
}

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// A sweep's output folder: one run directory per experiment (e.g. results/quick), or one
    /// `seed-S/` folder of them per seed.
    pub results: PathBuf,
    /// Write the report (tables, differences, plots, verdict.json, verdict.md, REPORT.md)
    /// here (default: RESULTS).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// How depth metrics are averaged over the test images: `per-image` (the authors'
    /// convention: per image, then the mean over images) or `pooled` (all pixels of the set).
    #[arg(long, default_value = "per-image")]
    pub averaging: calibconv::eval::metrics::Averaging,
    /// Seed of the paired bootstrap over test images.
    #[arg(long, default_value_t = 0)]
    pub bootstrap_seed: u64,
    /// Leave the point clouds' PLY files out (about 1.5 MB; the top-view picture is still
    /// drawn), removing those of an earlier report in OUT: for reports that are committed.
    #[arg(long)]
    pub no_ply: bool,
}

#[derive(Debug, Args)]
pub struct CameraArgs {
    #[command(subcommand)]
    pub command: CameraCommand,
}

#[derive(Debug, Subcommand)]
pub enum CameraCommand {
    /// Convert a calibration of Kalibr (camchain YAML), OpenCV (FileStorage YAML / XML / JSON),
    /// Basalt (calibration JSON), COLMAP (cameras.txt), OCamCalib (calib_results.txt), ROS
    /// camera_calibration (ost.yaml / ost.txt) or ORB-SLAM3 (settings YAML) into a camera file
    /// (TOML with named fields), checked like any camera file.
    Import(ImportArgs),
}

#[derive(Debug, Args)]
pub struct ImportArgs {
    /// Source tool: kalibr, opencv, basalt, colmap, ocamcalib, ros or orbslam3.
    #[arg(long = "from")]
    pub from: Format,
    /// The calibration file.
    pub file: PathBuf,
    /// Which camera: Kalibr camN, Basalt intrinsics[N], the N-th camera of a ROS ost.txt,
    /// ORB-SLAM3 0 (Camera1) or 1 (Camera2) (default 0); COLMAP CAMERA_ID (default: the first
    /// listed).
    #[arg(long)]
    pub camera: Option<usize>,
    /// Full field of view of a fisheye lens in degrees (default: the angle the image width
    /// spans on the principal row; calibration files rarely hold the lens's own).
    #[arg(long)]
    pub fov_deg: Option<f64>,
    /// OpenCV files only: fisheye or standard, when the file does not say (4 coefficients fit
    /// both).
    #[arg(long)]
    pub opencv_model: Option<OpenCvModel>,
    /// Output camera file (.toml), written atomically.
    #[arg(long)]
    pub out: PathBuf,
}

/// The experiment of `train` and `eval`, and how much they say while they run.
#[derive(Debug, Args)]
pub struct ExperimentArgs {
    /// Experiment file (TOML, see experiments/).
    pub experiment: PathBuf,
    /// No progress bars or status lines.
    #[arg(long, short)]
    pub quiet: bool,
}

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Continue the interrupted run at its last checkpoint (same step, same data order).
    #[arg(long)]
    pub resume: bool,
    #[command(flatten)]
    pub run: ExperimentArgs,
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Checkpoint to evaluate (default: the run's best, else its last).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Run only these evaluations (by name; repeatable).
    #[arg(long = "only", value_name = "NAME")]
    pub only: Vec<String>,
    #[command(flatten)]
    pub run: ExperimentArgs,
}

/// How the network input relates to the camera image.
#[derive(Debug, Args)]
pub struct FrameArgs {
    /// Padding added to the right and bottom of the camera image to form the network input,
    /// as `PW,PH` (the authors pad F195 by 2,0).
    #[arg(long, value_parser = parse_pair, default_value = "0,0")]
    pub padding: [usize; 2],
    /// Pixel-centre convention when scaling intrinsics: `half-pixel` (c' = (c + 0.5) s - 0.5)
    /// or `paper` (c' = c s, as the authors' code).
    #[arg(long, default_value = "half-pixel")]
    pub convention: PixelConvention,
}

#[derive(Debug, Args)]
pub struct OffsetsArgs {
    /// Camera file (TOML, see data/cameras/).
    #[arg(long)]
    pub camera: PathBuf,
    /// Input feature-map size as HxW (e.g. 240x272).
    #[arg(long, value_parser = parse_size)]
    pub size: [usize; 2],
    /// Kernel size (odd).
    #[arg(long, default_value_t = 3)]
    pub kernel: usize,
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    #[arg(long, default_value_t = 1)]
    pub dilation: usize,
    /// Zero padding of the convolution itself; default "same": dilation * (kernel - 1) / 2.
    #[arg(long)]
    pub conv_padding: Option<usize>,
    #[command(flatten)]
    pub frame: FrameArgs,
    /// Output file (.safetensors).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct KernelsArgs {
    /// Camera file (TOML, see data/cameras/).
    #[arg(long)]
    pub camera: PathBuf,
    /// Background image with the camera's size (default: the blank image circle).
    #[arg(long)]
    pub image: Option<PathBuf>,
    /// Feature-map downsampling factor the kernels are computed at.
    #[arg(long, default_value_t = 16)]
    pub level: usize,
    /// Kernel size (odd).
    #[arg(long, default_value_t = 3)]
    pub kernel: usize,
    /// Number of kernels along the longer side.
    #[arg(long, default_value_t = 9)]
    pub grid: usize,
    #[command(flatten)]
    pub frame: FrameArgs,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Camera file.
    #[arg(long, default_value = "data/cameras/f195.toml")]
    pub camera: PathBuf,
    /// Number of 2x2 poolings of the U-Net (the input is padded right/bottom to a multiple of
    /// 2^depth).
    #[arg(long, default_value_t = 4)]
    pub depth: usize,
    /// Output folder.
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// A few small shapes only (seconds).
    #[arg(long)]
    pub quick: bool,
    /// Every U-Net level (32..512 channels, 256x256..16x16) at batch 1, 4 and 8 (minutes).
    #[arg(long)]
    pub full: bool,
    /// Every 3x3 layer of the tiny (64x64, B8), small (128x128, B8) and classic (256x256, B2)
    /// U-Nets, first layers without input gradient (as in training); the training step of the
    /// quick profile's network (tiny, 64x64) and of the study profile's (small, depth 3,
    /// 144x160), B8 each.
    #[arg(long)]
    pub presets: bool,
    /// Also time the ATen composition (the CUDA path and the former CPU path).
    #[arg(long)]
    pub aten: bool,
    /// libtorch CPU threads (default: libtorch's choice; the quick sweep trains with 1).
    #[arg(long)]
    pub threads: Option<i32>,
    /// Skip the peak-memory pass (a second process).
    #[arg(long)]
    pub no_memory: bool,
    /// Internal: the peak-memory pass, run by `bench` itself in a child process.
    #[arg(long, hide = true)]
    pub memory_child: bool,
    /// Layer shapes to run instead of the table, each `B,CIN,COUT,H,W` (repeatable).
    #[arg(long = "shape", value_parser = parse_shape)]
    pub shapes: Vec<[i64; 5]>,
    /// Time the `--shape` layers as a network's first layer: the input (the image) needs no
    /// gradient, so forward+backward computes the weight and bias gradients only.
    #[arg(long, requires = "shapes")]
    pub first_layer: bool,
    /// Run only these parts (comma-separated; default: all).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub only: Vec<BenchPart>,
    /// Camera whose calibrated offsets the layers use.
    #[arg(long, default_value = "data/cameras/f195.toml")]
    pub camera: PathBuf,
    /// Also write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Cap the native few-output-channel kernels (AVX-512: 8 to 1024 outputs, weights up to 36 MiB;
    /// AVX2: 8 to 32) at
    /// this instruction-set level (`none`: such layers use the GEMM library like the others);
    /// default: the CPU's level. For A/B timings of the kernels on one machine.
    #[arg(long, value_enum)]
    pub small_kernels: Option<SmallKernelLevel>,
    /// The library of the float32 products the few-output-channel kernels do not take (layers
    /// of other output counts or larger weights: more than 1024 outputs or a weight over 36 MiB, and
    /// more than 32 outputs on CPUs without AVX-512;
    /// `auto`: the default, the BLAS). For A/B timings on one machine.
    #[arg(long, value_enum)]
    pub gemm: Option<GemmChoice>,
    /// The library of the products of large weights where the few-output-channel kernels exist
    /// (column and weight gradients of weights over 4 MiB, and their forward on fewer than 1024
    /// output pixels): `kernels`, `blas`,
    /// or `auto` (the default: the BLAS where it is MKL on an Intel CPU). For A/B timings.
    #[arg(long, value_enum)]
    pub large_weights: Option<LargeWeightsChoice>,
}

/// The library of `calibconv bench --large-weights`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LargeWeightsChoice {
    Auto,
    Kernels,
    Blas,
}

/// An instruction-set level of the few-output-channel kernels (`calibconv bench
/// --small-kernels`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SmallKernelLevel {
    None,
    Avx2,
    Avx512,
}

/// The GEMM library of `calibconv bench --gemm`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum GemmChoice {
    Auto,
    Onednn,
    Blas,
}

/// A part of `calibconv bench`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchPart {
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

fn parse_shape(s: &str) -> Result<[i64; 5], String> {
    let v: Vec<i64> = s
        .split(',')
        .map(|x| x.trim().parse::<i64>().ok().filter(|&n| n > 0))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("`{s}`: expected five positive integers B,CIN,COUT,H,W"))?;
    <[i64; 5]>::try_from(v).map_err(|_| format!("`{s}`: expected B,CIN,COUT,H,W"))
}

fn parse_size(s: &str) -> Result<[usize; 2], String> {
    let (h, w) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected HxW, e.g. 240x272"))?;
    let num = |v: &str| {
        v.trim()
            .parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("`{s}`: `{v}` is not a positive integer"))
    };
    Ok([num(h)?, num(w)?])
}

fn parse_pair(s: &str) -> Result<[usize; 2], String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("`{s}`: expected two integers as A,B"))?;
    let num = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{s}`: `{v}` is not a non-negative integer"))
    };
    Ok([num(a)?, num(b)?])
}
