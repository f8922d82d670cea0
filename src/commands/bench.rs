//! `calibconv bench`: flags to [`calibconv::bench::Options`], the camera, the peak-memory child
//! process (this binary again, with the same arguments and `--memory-child`) and the JSON file;
//! the benchmark itself is [`calibconv::bench`].

use anyhow::{bail, Context, Result};

use calibconv::bench::{self, MemoryReport, Options, Part};
use calibconv::io::write_bytes_atomic;
use calibconv::ops::{GemmLibrary, LargeWeights, NativeSetting, SmallKernelIsa};

use super::load_camera;
use crate::cli::{BenchArgs, BenchPart, GemmChoice, LargeWeightsChoice, SmallKernelLevel};

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
    if let Some(level) = args.small_kernels {
        SmallKernelIsa::set(Some(match level {
            SmallKernelLevel::None => SmallKernelIsa::None,
            SmallKernelLevel::Avx2 => SmallKernelIsa::Avx2,
            SmallKernelLevel::Avx512 => SmallKernelIsa::Avx512,
        }));
    }
    if let Some(choice) = args.gemm {
        GemmLibrary::set(match choice {
            GemmChoice::Auto => None,
            GemmChoice::Onednn => Some(GemmLibrary::OneDnn),
            GemmChoice::Blas => Some(GemmLibrary::Blas),
        });
    }
    if let Some(choice) = args.large_weights {
        LargeWeights::set(match choice {
            LargeWeightsChoice::Auto => None,
            LargeWeightsChoice::Kernels => Some(LargeWeights::Kernels),
            LargeWeightsChoice::Blas => Some(LargeWeights::Blas),
        });
    }
    let camera = load_camera(&args.camera)?;
    let options = Options {
        quick: args.quick,
        full: args.full,
        presets: args.presets,
        aten: args.aten,
        no_memory: args.no_memory,
        shapes: args.shapes.clone(),
        first_layer: args.first_layer,
        only: args.only.iter().map(|&p| part(p)).collect(),
        camera: args.camera.clone(),
    };
    if args.memory_child {
        return Ok(bench::memory_child(&camera, &options)?);
    }
    let report = bench::run(&camera, &options, || {
        memory_in_child().map_err(|e| format!("{e:#}"))
    })?;
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report)?;
        write_bytes_atomic(path, text.as_bytes())
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("\nwrote {}", path.display());
    }
    Ok(())
}

fn part(p: BenchPart) -> Part {
    match p {
        BenchPart::Layers => Part::Layers,
        BenchPart::Pyramid => Part::Pyramid,
        BenchPart::Unet => Part::Unet,
        BenchPart::Functional => Part::Functional,
    }
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
