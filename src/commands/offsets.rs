//! `calibconv offsets`: one layer's calibrated offsets to safetensors.

use std::time::Instant;

use anyhow::{bail, Result};

use calibconv::kernel::{compute_offsets, LayerGeometry, OffsetsTensor};

use super::{frame, load_camera, write_safetensors};
use crate::cli::OffsetsArgs;

pub fn run(args: OffsetsArgs) -> Result<()> {
    let camera = load_camera(&args.camera)?;
    if args.kernel.is_multiple_of(2) || args.stride == 0 || args.dilation == 0 {
        bail!("--kernel must be odd, --stride and --dilation at least 1");
    }
    let pad = args
        .conv_padding
        .unwrap_or(args.dilation * (args.kernel - 1) / 2);
    let geometry = LayerGeometry {
        kernel: [args.kernel; 2],
        stride: [args.stride; 2],
        padding: [pad; 2],
        dilation: [args.dilation; 2],
    };
    let start = Instant::now();
    let off = compute_offsets(&camera, args.size, &geometry, &frame(&args.frame))?;
    let secs = start.elapsed().as_secs_f64();
    write_safetensors(&args.out, &[("offsets".to_string(), off.to_tensor())])?;
    println!(
        "{}: offsets [{}, {}, {}] for a {}x{} input ({} stride {} dilation {} padding {}), \
         max |offset| {:.3} px, {} anchors outside the model, {:.1} ms",
        args.out.display(),
        2 * args.kernel * args.kernel,
        off.output_size[0],
        off.output_size[1],
        args.size[0],
        args.size[1],
        args.kernel,
        args.stride,
        args.dilation,
        pad,
        off.max_abs(),
        off.fallback_anchors,
        secs * 1e3
    );
    Ok(())
}
