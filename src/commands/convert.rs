//! `calibconv convert MODEL.pth --out W.safetensors`: a PyTorch checkpoint to safetensors with
//! a JSON sidecar, by `tools/convert_checkpoint.py` in the project's Python environment (reading
//! `.pth` pickles needs `torch`). The result is a valid `model.init.checkpoint` of an experiment.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};
use clap::Args;

use calibconv::train::checkpoint::TensorFile;
use calibconv::train::pytorch::TorchArchitecture;

/// The converter, relative to the crate root.
const SCRIPT: &str = "tools/convert_checkpoint.py";
/// The Python environment `make setup` links, relative to the crate root.
const VENV_PYTHON: &str = ".venv/bin/python";

#[derive(Debug, Args)]
pub struct ConvertArgs {
    /// PyTorch checkpoint (.pth / .pt): a state_dict, bare or under `state_dict` / `model` /
    /// `net`, with or without DataParallel's `module.` prefix (e.g. milesial/Pytorch-UNet's).
    pub checkpoint: PathBuf,
    /// Output safetensors file; the JSON sidecar (key mapping, dtypes, detected architecture)
    /// is written next to it with the extension .json.
    #[arg(long)]
    pub out: PathBuf,
    /// Python interpreter with torch and safetensors (default: .venv/bin/python of the crate
    /// root: the current directory or one above it, else the crate this binary was built from).
    #[arg(long)]
    pub python: Option<PathBuf>,
}

/// The crate root holding the converter: the current directory or an ancestor, else the
/// directory this binary was built from.
fn crate_root() -> Option<PathBuf> {
    let cwd = std::env::current_dir().ok();
    cwd.iter()
        .flat_map(|d| d.ancestors())
        .map(Path::to_path_buf)
        .chain(std::iter::once(PathBuf::from(env!("CARGO_MANIFEST_DIR"))))
        .find(|d| d.join(SCRIPT).is_file())
}

pub fn run(args: ConvertArgs) -> Result<()> {
    if !args.checkpoint.is_file() {
        bail!("{}: no such file", args.checkpoint.display());
    }
    let Some(root) = crate_root() else {
        bail!(
            "cannot find {SCRIPT} in the current directory, its parents or {}",
            env!("CARGO_MANIFEST_DIR")
        );
    };
    let python = args
        .python
        .clone()
        .unwrap_or_else(|| root.join(VENV_PYTHON));
    if !python.is_file() {
        bail!(
            "no Python environment at {}: run `make setup` in {} (or pass --python)",
            python.display(),
            root.display()
        );
    }
    let status = Command::new(&python)
        .arg(root.join(SCRIPT))
        .arg(&args.checkpoint)
        .arg(&args.out)
        .status()
        .with_context(|| format!("cannot run {}", python.display()))?;
    if !status.success() {
        bail!(
            "converting {} failed ({status}; the converter's message is above)",
            args.checkpoint.display()
        );
    }
    // Read back what was written: a readable safetensors file with its architecture record.
    let file = TensorFile::open(&args.out)
        .with_context(|| format!("the converter's output {}", args.out.display()))?;
    match TorchArchitecture::of_file(&args.out, &file)? {
        Some(a) => println!(
            "use it as `model.init = {{ checkpoint = \"{}\" }}` of an experiment with \
             in_channels {}, {} {}, base {}, depth {}, up = \"{}\" (either kernel)",
            args.out.display(),
            a.in_channels,
            a.classes,
            if a.classes == 1 {
                "output channel (task depth, or 1 class)"
            } else {
                "classes"
            },
            a.base,
            a.depth,
            a.variant
        ),
        None => eprintln!(
            "warning: {} is not a milesial/Pytorch-UNet state_dict; loading will check names \
             and shapes only",
            args.checkpoint.display()
        ),
    }
    Ok(())
}
