//! What each subcommand does, one file per subcommand (the library does the work; these files
//! wire files and output). Shared helpers live here.

mod bench;
mod bench_device;
mod camera;
pub(crate) mod convert;
mod demo;
mod eval;
pub(crate) mod export;
mod info;
mod kernels;
mod offsets;
mod report;
mod sweep;
pub(crate) mod synth;
mod train;

use std::io::IsTerminal;
use std::path::Path;

use anyhow::{Context, Result};
use tch::Tensor;

use calibconv::camera::Camera;
use calibconv::data::synth::DEFAULT_CAMERAS;
use calibconv::experiment::{self, DefaultOpener, Experiment, RunOptions};
use calibconv::io::{write_atomic, write_png_atomic};
use calibconv::kernel::InputFrame;
use calibconv::train::stop::StopFlag;

use crate::cli::{Command, ExperimentArgs, FrameArgs};

pub fn run(command: Command) -> Result<()> {
    match command {
        Command::Offsets(args) => offsets::run(args),
        Command::Kernels(args) => kernels::run(args),
        Command::Demo(args) => demo::run(args),
        Command::Bench(args) => bench::run(args),
        Command::BenchDevice(args) => bench_device::run(args),
        Command::Synth(args) => synth::run(args),
        Command::Camera(args) => camera::run(args),
        Command::Train(args) => train::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Info(args) => info::run(args),
        Command::Convert(args) => convert::run(args),
        Command::Export(args) => export::run(args),
        Command::Sweep(args) => sweep::run(args),
        Command::Report(args) => report::run(args),
    }
}

impl ExperimentArgs {
    /// The experiment file, loaded and resolved.
    fn load(&self) -> Result<Experiment> {
        experiment::load(&self.experiment)
            .with_context(|| format!("cannot use experiment {}", self.experiment.display()))
    }

    /// How `train` and `eval` run it: progress bars on a terminal and status lines unless
    /// `--quiet`, the data sources of the command line.
    fn options(&self, resume: bool, stop: StopFlag) -> RunOptions<'static> {
        RunOptions {
            resume,
            progress: !self.quiet && std::io::stderr().is_terminal(),
            verbose: !self.quiet,
            opener: &DefaultOpener,
            stop,
        }
    }
}

fn frame(args: &FrameArgs) -> InputFrame {
    InputFrame {
        padding: args.padding,
        convention: args.convention,
    }
}

/// A camera file. A path that does not exist from the working directory but names one of the
/// shipped cameras as the defaults spell them (`data/cameras/f195.toml`, ...) reads the copy
/// embedded in the binary ([`DEFAULT_CAMERAS`], the same bytes `synth`'s embedded default
/// reads), so a default `--camera` works outside the repository too.
fn load_camera(path: &Path) -> Result<Camera> {
    let embedded = DEFAULT_CAMERAS
        .iter()
        .find(|(name, _)| Path::new(name) == path);
    match embedded {
        Some((name, text)) if !path.exists() => calibconv::camera::parse(text, Path::new(name)),
        _ => calibconv::camera::load(path),
    }
    .with_context(|| format!("cannot use camera file {}", path.display()))
}

fn write_safetensors(path: &Path, tensors: &[(String, Tensor)]) -> Result<()> {
    write_atomic(path, |tmp| Ok(Tensor::write_safetensors(tensors, tmp)?))
        .with_context(|| format!("cannot write {}", path.display()))
}

fn save_png(path: &Path, img: &image::RgbImage) -> Result<()> {
    write_png_atomic(path, img).with_context(|| format!("cannot write {}", path.display()))
}
