//! `calibconv demo`: the main job on the embedded default data.

use std::time::Instant;

use anyhow::{bail, Result};
use tch::{Device, Kind, Tensor};

use calibconv::camera::{Camera, CameraModel};
use calibconv::io::write_bytes_atomic;
use calibconv::kernel::{
    compute_offsets, pyramid_sizes, InputFrame, LayerGeometry, Offsets, OffsetsTensor,
};
use calibconv::nn::{CalibratedConv2d, CameraInput, Conv2dConfig};
use calibconv::report::kernels::{draw_kernels, image_circle, KernelFigure};

use super::{load_camera, save_png, write_safetensors};
use crate::cli::DemoArgs;

/// Times `f` (after one warm-up call) over `reps` calls, in milliseconds per call.
fn time_ms(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    for _ in 0..reps {
        f();
    }
    start.elapsed().as_secs_f64() * 1e3 / reps as f64
}

/// The offsets of a pyramid, as saved and summarised.
struct PyramidOffsets {
    /// `levelL`, the offsets of level `L`.
    tensors: Vec<(String, Tensor)>,
    /// A summary per level for `summary.json`.
    levels: Vec<serde_json::Value>,
    /// How long computing them took.
    seconds: f64,
}

/// The offsets of every level of `sizes` (3x3, stride 1, "same"), printed level by level.
fn pyramid_offsets(
    camera: &Camera,
    sizes: &[[usize; 2]],
    frame: &InputFrame,
) -> Result<PyramidOffsets> {
    let start = Instant::now();
    let levels: Vec<Offsets> = sizes
        .iter()
        .map(|&size| compute_offsets(camera, size, &LayerGeometry::same(3), frame))
        .collect::<Result<_, calibconv_geometry::Error>>()?;
    let offsets_secs = start.elapsed().as_secs_f64();
    let anchors: usize = sizes.iter().map(|s| s[0] * s[1]).sum();
    let mut summary_levels = Vec::new();
    let mut tensors = Vec::new();
    for (l, off) in levels.iter().enumerate() {
        println!(
            "  level {l}: {:>4}x{:<4} max |offset| {:7.3} px, anchors outside the model {}",
            off.input_size[0],
            off.input_size[1],
            off.max_abs(),
            off.fallback_anchors
        );
        tensors.push((format!("level{l}"), off.to_tensor()));
        summary_levels.push(serde_json::json!({
            "level": l,
            "size_hw": off.input_size,
            "max_abs_offset_px": off.max_abs(),
            "fallback_anchors": off.fallback_anchors,
            "fallback_taps": off.fallback_taps,
        }));
    }
    println!(
        "offsets for {anchors} anchors x 9 taps in {:.3} s ({:.2} us per anchor)",
        offsets_secs,
        offsets_secs * 1e6 / anchors as f64
    );
    Ok(PyramidOffsets {
        tensors,
        levels: summary_levels,
        seconds: offsets_secs,
    })
}

/// Times a 16->16 calibrated convolution at `[fh, fw]` against `conv2d`, forward + backward,
/// in milliseconds per call; an error if the calibrated output is not finite.
fn time_calibrated_conv(
    camera: &Camera,
    frame: &InputFrame,
    [fh, fw]: [i64; 2],
) -> Result<(f64, f64)> {
    let vs = tch::nn::VarStore::new(Device::Cpu);
    let conv = CalibratedConv2d::new(
        &vs.root(),
        16,
        16,
        3,
        CameraInput::new(camera, frame, [fh, fw]),
        Conv2dConfig::default(),
    )?;
    tch::manual_seed(0);
    let x = Tensor::randn([1, 16, fh, fw], (Kind::Float, Device::Cpu)).set_requires_grad(true);
    let mut calibrated_out = None;
    let cal_ms = time_ms(3, || {
        let y = conv.f_forward(&x).expect("calibrated forward");
        y.sum(Kind::Float).backward();
        calibrated_out = Some(y.detach());
    });
    let std_ms = time_ms(3, || {
        let y = x.conv2d(&conv.ws, conv.bs.as_ref(), [1, 1], [1, 1], [1, 1], 1);
        y.sum(Kind::Float).backward();
    });
    let finite = calibrated_out
        .map(|y| y.isfinite().all().int64_value(&[]) == 1)
        .unwrap_or(false);
    if !finite {
        bail!("the calibrated convolution produced non-finite values");
    }
    Ok((cal_ms, std_ms))
}

pub fn run(args: DemoArgs) -> Result<()> {
    let camera = load_camera(&args.camera)?;
    let [w, h] = camera.size();
    let m = 1usize << args.depth;
    let frame = InputFrame {
        padding: [(m - w % m) % m, (m - h % m) % m],
        ..Default::default()
    };
    let input = [h + frame.padding[1], w + frame.padding[0]];
    let sizes = pyramid_sizes(input, args.depth);
    println!(
        "camera {} ({w}x{h}, FOV {:.0} deg), network input {}x{} (padding {:?}), {} levels",
        args.camera.display(),
        camera.fov().to_degrees(),
        input[0],
        input[1],
        frame.padding,
        sizes.len()
    );

    // 1. Offsets for every level of the pyramid (3x3, stride 1, "same"), timed.
    let PyramidOffsets {
        tensors,
        levels: summary_levels,
        seconds: offsets_secs,
    } = pyramid_offsets(&camera, &sizes, &frame)?;
    let anchors: usize = sizes.iter().map(|s| s[0] * s[1]).sum();
    let offsets_path = args.out.join("pyramid_offsets.safetensors");
    write_safetensors(&offsets_path, &tensors)?;

    // 2. The kernel figure.
    let fig = KernelFigure {
        frame,
        ..Default::default()
    };
    let figure_path = args.out.join("kernels.png");
    save_png(
        &figure_path,
        &draw_kernels(&camera, image_circle(&camera), &fig)?,
    )?;

    // 3. A calibrated convolution at the third level, forward + backward, against conv2d.
    let level = sizes.len().min(3) - 1;
    let [fh, fw] = sizes[level].map(|v| v as i64);
    let (cal_ms, std_ms) = time_calibrated_conv(&camera, &frame, [fh, fw])?;
    println!(
        "calibrated conv 16->16 at {fh}x{fw}, forward+backward: {cal_ms:.1} ms vs conv2d {std_ms:.1} ms ({:.1}x)",
        cal_ms / std_ms
    );

    let summary = serde_json::json!({
        "camera": args.camera,
        "camera_size_wh": [w, h],
        "fov_deg": camera.fov().to_degrees(),
        "input_padding_wh": frame.padding,
        "convention": "half-pixel",
        "levels": summary_levels,
        "offsets_seconds": offsets_secs,
        "anchors": anchors,
        "conv_benchmark": {
            "level": level, "size_hw": [fh, fw], "channels": 16,
            "calibrated_fwd_bwd_ms": cal_ms, "conv2d_fwd_bwd_ms": std_ms,
        },
        "threads": rayon::current_num_threads(),
    });
    let summary_path = args.out.join("summary.json");
    write_bytes_atomic(
        &summary_path,
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    println!(
        "wrote {}, {} and {}",
        offsets_path.display(),
        figure_path.display(),
        summary_path.display()
    );
    Ok(())
}
