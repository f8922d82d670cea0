//! `calibconv kernels`: the deformed-kernel figure.

use anyhow::Result;

use calibconv::report::kernels::{draw_kernels, image_circle, load_background, KernelFigure};

use super::{frame, load_camera, save_png};
use crate::cli::KernelsArgs;

pub fn run(args: KernelsArgs) -> Result<()> {
    let camera = load_camera(&args.camera)?;
    let background = match &args.image {
        Some(path) => load_background(path, &camera)?,
        None => image_circle(&camera),
    };
    let fig = KernelFigure {
        level: args.level,
        kernel: args.kernel,
        grid: args.grid,
        frame: frame(&args.frame),
    };
    let img = draw_kernels(&camera, background, &fig)?;
    save_png(&args.out, &img)?;
    println!(
        "{}: {}x{} kernel figure",
        args.out.display(),
        img.width(),
        img.height()
    );
    Ok(())
}
