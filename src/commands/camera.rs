//! `calibconv camera import`: another tool's calibration as a camera file.

use anyhow::{Context, Result};

use calibconv::camera::import::{import_file, ImportOptions};
use calibconv::camera::{to_toml, CameraModel};
use calibconv::io::write_bytes_atomic;

use crate::cli::{CameraArgs, CameraCommand, ImportArgs};

pub fn run(args: CameraArgs) -> Result<()> {
    match args.command {
        CameraCommand::Import(args) => import(args),
    }
}

fn import(args: ImportArgs) -> Result<()> {
    let options = ImportOptions {
        camera: args.camera,
        fov_deg: args.fov_deg,
        opencv_model: args.opencv_model,
    };
    let imported = import_file(args.from, &args.file, &options)
        .with_context(|| format!("cannot import a {} calibration", args.from))?;
    let file_name = args.file.file_name().map_or_else(
        || args.file.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    let name = args
        .out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned());
    let description = format!("imported from {file_name}: {}", imported.source);
    let mut header = vec![format!(
        "Written by `calibconv camera import --from {}` from {file_name}: {}.",
        args.from, imported.source
    )];
    header.extend(imported.notes.iter().cloned());
    let text = to_toml(
        &imported.camera,
        &header,
        name.as_deref(),
        Some(&description),
    );
    write_bytes_atomic(&args.out, text.as_bytes())
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    let [w, h] = imported.camera.size();
    println!(
        "{}: {} camera {w}x{h}, field of view {:.3} deg, from {}",
        args.out.display(),
        imported.camera.model_name(),
        imported.camera.fov().to_degrees(),
        imported.source
    );
    if imported.outside > 0.0 {
        println!(
            "{:.2} % of the image lies outside the model (its pixels do not unproject)",
            100.0 * imported.outside
        );
    }
    Ok(())
}
