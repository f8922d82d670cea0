//! The `calibconv` binary end to end: files written, shapes, and clear errors on bad input.

use std::path::Path;

use calibconv::camera;
use calibconv::kernel::{compute_offsets, InputFrame, LayerGeometry, OffsetsTensor};

use crate::common::{self, assert_contains, calibconv, failed, ok, s, words};

fn camera_file(name: &str) -> String {
    format!("{}/data/cameras/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// `calibconv offsets` of `camera` at `size` to `out`, with `extra` flags.
fn offsets(camera: &str, size: &str, extra: &[&str], out: &Path) -> std::process::Output {
    let args = [
        "offsets",
        "--camera",
        camera,
        "--size",
        size,
        "--out",
        s(out),
    ];
    calibconv(&[&args[..], extra].concat())
}

fn read_offsets(path: &Path) -> tch::Tensor {
    let mut tensors = tch::Tensor::read_safetensors(path).expect("read safetensors");
    assert_eq!(tensors.len(), 1);
    let (name, t) = tensors.pop().unwrap();
    assert_eq!(name, "offsets");
    t
}

#[test]
fn offsets_writes_the_library_offsets_in_torchvision_layout() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o.safetensors");
    let extra = ["--kernel", "3", "--padding", "8,0"];
    ok(offsets(&camera_file("f195.toml"), "240x272", &extra, &out));
    let t = read_offsets(&out);
    assert_eq!(t.size(), [18, 240, 272]);
    let cam = camera::load(camera_file("f195.toml")).unwrap();
    let frame = InputFrame {
        padding: [8, 0],
        ..Default::default()
    };
    let lib = compute_offsets(&cam, [240, 272], &LayerGeometry::same(3), &frame).unwrap();
    assert!(t.equal(&lib.to_tensor()));
}

#[test]
fn offsets_with_stride_dilation_and_paper_convention() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s2.safetensors");
    let extra = words("--kernel 5 --stride 2 --dilation 2 --convention paper");
    ok(offsets(&camera_file("f165.toml"), "60x68", &extra, &out));
    // Same padding 4 with dilation 2: (60 + 8 - 9) / 2 + 1 = 30, (68 + 8 - 9) / 2 + 1 = 34.
    assert_eq!(read_offsets(&out).size(), [50, 30, 34]);
}

#[test]
fn bad_camera_file_is_a_clear_error_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cam = dir.path().join("typo.toml");
    let text = std::fs::read_to_string(camera_file("f195.toml"))
        .unwrap()
        .replace("fx =", "fxx =");
    std::fs::write(&cam, text).unwrap();
    let out = dir.path().join("o.safetensors");
    let err = failed(offsets(s(&cam), "24x27", &[], &out));
    assert_contains(&err, &["typo.toml", "fxx"]);
    assert!(!out.exists());
}

#[test]
fn bad_arguments_exit_non_zero() {
    let f195 = "data/cameras/f195.toml";
    for (camera, size, extra) in [
        (f195, "24by27", &[][..]),
        (f195, "24x27", &["--kernel", "4"][..]),
        ("data/cameras/missing.toml", "24x27", &[][..]),
        (f195, "24x27", &["--convention", "corner"][..]),
    ] {
        let o = offsets(camera, size, extra, Path::new("x"));
        let args = format!("--camera {camera} --size {size} {extra:?}");
        assert!(!o.status.success(), "{args} should fail");
        assert!(!common::stderr(&o).is_empty(), "{args}");
    }
    assert!(!common::root().join("x").exists());
}

/// A size whose offsets cannot be held is a clear error before anything is allocated, not an
/// allocation failure that aborts with a backtrace.
#[test]
fn offsets_too_large_to_allocate_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("huge.safetensors");
    let o = offsets("data/cameras/f195.toml", "100000x100000", &[], &out);
    let err = common::stderr(&o);
    // Exit status 1 (an error), not a signal (SIGABRT).
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_contains(&err, &["100000x100000", "too large"]);
    assert!(!err.contains("memory allocation"), "{err}");
    assert!(!out.exists());
}

#[test]
fn kernels_draws_a_png_of_the_camera_size_and_rejects_a_wrong_image() {
    let dir = tempfile::tempdir().unwrap();
    let f195 = camera_file("f195.toml");
    let png = dir.path().join("k.png");
    ok(calibconv(&["kernels", "--camera", &f195, "--out", s(&png)]));
    let img = image::open(&png).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (1080, 960));
    // Kernel taps are drawn in colour on the grey/black background.
    assert!(img.pixels().any(|p| p.0[0] > 200 && p.0[2] < 100));

    let small = dir.path().join("small.png");
    image::RgbImage::new(64, 48).save(&small).unwrap();
    let png2 = dir.path().join("k2.png");
    let args = [
        "kernels",
        "--camera",
        &f195,
        "--image",
        s(&small),
        "--out",
        s(&png2),
    ];
    let err = failed(calibconv(&args));
    assert_contains(&err, &["small.png", "64x48"]);
}

#[test]
fn demo_writes_pyramid_offsets_figure_and_summary() {
    let dir = tempfile::tempdir().unwrap();
    let f165 = camera_file("f165.toml");
    ok(calibconv(&[
        "demo",
        "--camera",
        &f165,
        "--depth",
        "3",
        "--out",
        s(dir.path()),
    ]));
    let tensors =
        tch::Tensor::read_safetensors(dir.path().join("pyramid_offsets.safetensors")).unwrap();
    let mut names: Vec<_> = tensors.iter().map(|(n, t)| (n.clone(), t.size())).collect();
    names.sort();
    // 1080x960 padded to multiples of 8: 1080 and 960 already are.
    assert_eq!(names[0], ("level0".to_string(), vec![18, 960, 1080]));
    assert_eq!(names[3], ("level3".to_string(), vec![18, 120, 135]));
    assert!(dir.path().join("kernels.png").exists());
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["levels"].as_array().unwrap().len(), 4);
    assert!(summary["offsets_seconds"].as_f64().unwrap() > 0.0);
}
