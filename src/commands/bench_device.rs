//! `calibconv bench-device`: layer and U-Net step timings on a device (see
//! [`calibconv::bench::device`]); each step's peak memory in a child process per kernel kind
//! (this binary again with `--memory-child KERNEL`).

use std::process::Command;

use anyhow::{bail, ensure, Context, Result};
use serde::Serialize;

use calibconv::bench::device::{layer_row, step_memory, step_row, unet_layers, LayerRow, StepRow};
use calibconv::device::{describe, RuntimeInfo};
use calibconv::io::write_bytes_atomic;

use super::load_camera;
use crate::cli::BenchDeviceArgs;

/// The JSON `--json` writes.
#[derive(Serialize)]
struct Record {
    device: String,
    runtime: RuntimeInfo,
    layers: Vec<LayerRow>,
    steps: Vec<StepRow>,
    /// Rows that failed (an error or a panic inside libtorch, e.g. out of memory): what, why.
    failed: Vec<(String, String)>,
}

/// `f()`, with a panic (tch panics on libtorch errors in its non-`f_` calls) turned into an
/// error carrying its message.
fn guarded<T>(f: impl FnOnce() -> calibconv::Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => Ok(r?),
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "panic".into());
            bail!("{}", msg.lines().next().unwrap_or(""))
        }
    }
}

/// `PRESET:HxW:B`.
fn parse_spec(s: &str) -> Result<(String, [i64; 2], i64)> {
    let parts: Vec<&str> = s.split(':').collect();
    let [preset, size, batch] = parts.as_slice() else {
        bail!("`{s}`: expected PRESET:HxW:B, e.g. classic:1088x960:8");
    };
    let (h, w) = size
        .split_once('x')
        .with_context(|| format!("`{s}`: size must be HxW"))?;
    Ok((
        preset.to_string(),
        [h.parse().context("height")?, w.parse().context("width")?],
        batch.parse().with_context(|| format!("`{s}`: batch"))?,
    ))
}

pub fn run(args: BenchDeviceArgs) -> Result<()> {
    let device =
        calibconv::device::resolve(&args.device, "calibconv bench-device".as_ref(), "--device")?;
    let camera = load_camera(&args.camera)?;
    if let Some(kernel) = &args.memory_child {
        ensure!(args.steps.len() == 1, "--memory-child takes one --step");
        let (preset, size, batch) = parse_spec(&args.steps[0])?;
        println!(
            "{}",
            guarded(|| step_memory(&camera, &preset, kernel, size, batch, device))?
        );
        return Ok(());
    }
    ensure!(args.reps >= 1, "--reps must be >= 1");
    let (mut layers, mut failed) = (Vec::new(), Vec::new());
    for spec in &args.layers {
        let (preset, size, batch) = parse_spec(spec)?;
        for layer in unet_layers(&preset, size, batch)? {
            let row = match guarded(|| layer_row(&camera, &layer, device, args.reps)) {
                Ok(row) => row,
                Err(e) => {
                    println!("{:<48} FAILED: {e:#}", layer.name);
                    failed.push((layer.name.clone(), format!("{e:#}")));
                    continue;
                }
            };
            println!(
                "{:<48} conv2d {:>9.3} ms  calibrated {:>9.3} ms  fwd {:.2}x  f+b {:.2}x",
                row.layer, row.cudnn_ms, row.calibrated_ms, row.ratio_fwd, row.ratio_fb
            );
            layers.push(row);
        }
    }
    let mut steps = Vec::new();
    for spec in &args.steps {
        let (preset, size, batch) = parse_spec(spec)?;
        let mut row = match guarded(|| step_row(&camera, &preset, size, batch, device, args.reps)) {
            Ok(row) => row,
            Err(e) => {
                println!("{spec} step FAILED: {e:#}");
                failed.push((format!("{spec} step"), format!("{e:#}")));
                continue;
            }
        };
        if !args.no_memory {
            for (kernel, slot) in [
                ("standard", &mut row.standard_peak_gib),
                ("calibrated", &mut row.calibrated_peak_gib),
            ] {
                match memory_child(&args, spec, kernel) {
                    Ok(gib) => *slot = Some(gib),
                    Err(e) => failed.push((format!("{spec} {kernel} memory"), format!("{e:#}"))),
                }
            }
        }
        println!(
            "{spec} step: standard {:.1} ms, calibrated {:.1} ms, {:.2}x; peak {} / {} GiB",
            row.standard_ms,
            row.calibrated_ms,
            row.ratio,
            fmt_gib(row.standard_peak_gib),
            fmt_gib(row.calibrated_peak_gib)
        );
        steps.push(row);
    }
    if let Some(path) = &args.json {
        let record = Record {
            device: describe(device),
            runtime: RuntimeInfo::read(),
            layers,
            steps,
            failed: failed.clone(),
        };
        write_bytes_atomic(path, serde_json::to_string_pretty(&record)?.as_bytes())?;
    }
    ensure!(failed.is_empty(), "{} row(s) failed", failed.len());
    Ok(())
}

fn fmt_gib(v: Option<f64>) -> String {
    v.map_or("-".into(), |g| format!("{g:.2}"))
}

/// Runs this binary as the memory child of one step and reads its answer (GiB).
fn memory_child(args: &BenchDeviceArgs, spec: &str, kernel: &str) -> Result<f64> {
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let out = Command::new(exe)
        .arg("bench-device")
        .args([
            "--device",
            &args.device,
            "--step",
            spec,
            "--memory-child",
            kernel,
        ])
        .arg("--camera")
        .arg(&args.camera)
        .output()
        .context("cannot run the memory child")?;
    ensure!(
        out.status.success(),
        "memory child ({spec}, {kernel}) failed: {}",
        String::from_utf8_lossy(&out.stderr).trim()
    );
    let text = String::from_utf8_lossy(&out.stdout);
    text.trim()
        .parse()
        .with_context(|| format!("memory child ({spec}, {kernel}) printed {text:?}"))
}
