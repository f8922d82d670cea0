//! PyTorch checkpoints both ways, against the reference milesial/Pytorch-UNet of
//! `tools/reference_unet.py`, with fixtures made at test time by `tools/make_pytorch_parity.py`
//! in `.venv` (these tests fail, they do not skip, without it: run `make setup`).
//!
//! - torch -> calibconv: random weights (BatchNorm running statistics too) saved as milesial's
//!   `train.py` does (`state_dict` + `mask_values`) and as a nested, `module.`-prefixed,
//!   channels-last checkpoint; `calibconv convert`; loaded into `calibconv::nn::UNet`; the same
//!   input in eval mode gives PyTorch's output, for transposed and bilinear up-sampling.
//! - calibconv -> torch: a calibconv checkpoint (random, and fine-tuned by an experiment from a
//!   converted checkpoint); `calibconv export`; PyTorch loads it with
//!   `load_state_dict(strict=True)` and gives calibconv's output.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};

use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use calibconv::experiment::{self, Experiment};
use calibconv::kernel::InputFrame;
use calibconv::nn::{ConvKind, Head, UNet, UNetConfig, UpMode};
use calibconv::train;
use calibconv::train::checkpoint::{self, CheckpointInfo};

use crate::common::experiment::{quiet, ExperimentFile};
use crate::common::{self, calibconv, failed, max_rel, ok, read_safetensors, root, s};

/// float32 convolutions, BatchNorm and up-sampling by one libtorch from two front ends; the
/// issue's bound. Observed: 0 (bit-identical) on this machine; other thread counts reorder sums.
const TOL: f64 = 1e-4;
/// The fixture network: milesial's blocks at base 8, depth 4, 3 inputs, 3 classes.
const SIZE: [i64; 2] = [37, 45];
const MODES: [(&str, UpMode); 2] = [
    ("transposed", UpMode::Transposed),
    ("bilinear", UpMode::Bilinear),
];

fn config(up: UpMode) -> UNetConfig {
    UNetConfig {
        in_channels: 3,
        base: 8,
        depth: 4,
        up,
        head: Head::Segmentation { classes: 3 },
    }
}

/// Runs `tools/make_pytorch_parity.py` with `.venv/bin/python`; panics with its output on
/// failure, or if the environment is missing.
fn python(args: &[&Path]) {
    let py = root().join(".venv/bin/python");
    assert!(
        py.is_file(),
        "{} is missing: run `make setup` (these tests need torch)",
        py.display()
    );
    let out = Command::new(&py)
        .arg(root().join("tools/make_pytorch_parity.py"))
        .args(args)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "make_pytorch_parity.py {args:?}: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `calibconv convert` or `calibconv export` (`command`) of `file` to `out`, which must succeed.
fn convert(command: &str, file: &Path, out: &Path) {
    ok(calibconv(&[command, s(file), "--out", s(out)]));
}

/// The PyTorch fixtures, made once per test run, with each `.pth` converted by
/// `calibconv convert` (`MODE[_nested].safetensors` + `.json`).
fn fixtures() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("pytorch_parity");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        python(&[Path::new("torch-to-rust"), &dir]);
        for (mode, _) in MODES {
            for suffix in ["", "_nested", "_1class"] {
                let pth = dir.join(format!("{mode}{suffix}.pth"));
                let out = dir.join(format!("{mode}{suffix}.safetensors"));
                convert("convert", &pth, &out);
            }
        }
        dir
    })
}

fn f195() -> ConvKind {
    let camera = calibconv::camera::load(root().join("data/cameras/f195.toml")).unwrap();
    ConvKind::Calibrated {
        camera: Arc::new(camera),
        frame: InputFrame::default(),
    }
}

#[test]
fn converted_pytorch_checkpoints_give_pytorchs_outputs_in_eval_mode() {
    let dir = fixtures();
    for (mode, up) in MODES {
        let io = read_safetensors(&dir.join(format!("{mode}_io.safetensors")));
        let mut weights: Vec<BTreeMap<String, Tensor>> = Vec::new();
        for suffix in ["", "_nested"] {
            let what = format!("{mode}{suffix}");
            let file = dir.join(format!("{what}.safetensors"));
            let sidecar: serde_json::Value =
                serde_json::from_str(&common::read_text(&file.with_extension("json"))).unwrap();
            assert_eq!(sidecar["architecture"]["variant"], mode, "{what}");
            if suffix.is_empty() {
                // milesial's train.py adds the data set's mask values: recorded, not a tensor.
                assert_eq!(sidecar["dropped"][0]["key"], "mask_values", "{what}");
            } else {
                assert_eq!(
                    sidecar["key_mapping"]["module.outc.conv.bias"],
                    "outc.conv.bias"
                );
                assert_eq!(sidecar["outside_state_dict"][1]["key"], "mask_values");
            }
            let cfg = config(up);
            let vs = VarStore::new(Device::Cpu);
            let net = UNet::new(&vs.root(), &cfg, &ConvKind::Standard, SIZE).unwrap();
            let loaded = checkpoint::load(&file, &vs, &cfg).unwrap();
            assert!(loaded.torch_architecture.is_some(), "{what}");
            // 2 BatchNorms in each of 1 + 2 * depth DoubleConvs: their counters are dropped.
            assert_eq!(loaded.ignored.len(), 18, "{what}");
            let y = tch::no_grad(|| net.f_forward_raw_t(&io["input"], false)).unwrap();
            let e = max_rel(&y, &io["output"]);
            eprintln!("torch -> calibconv, {what}: max relative error {e:.3e}");
            assert!(e < TOL, "{what}: {e}");
            weights.push(checkpoint::named_variables(&vs).into_iter().collect());
        }
        // The channels-last, prefixed, nested checkpoint holds exactly the same values.
        for (name, t) in &weights[0] {
            assert!(t.equal(&weights[1][name]), "{mode}: {name}");
        }
    }
}

#[test]
fn milesials_own_size_converts_loads_into_the_classic_presets_and_matches() {
    // Base 64 (31 M / 17 M parameters): the presets are milesial's network, not just alike.
    let dir = tempfile::tempdir().unwrap();
    python(&[Path::new("classic"), dir.path()]);
    for (mode, preset) in [("transposed", "classic"), ("bilinear", "classic-bilinear")] {
        let pth = dir.path().join(format!("classic_{mode}.pth"));
        let file = dir.path().join(format!("classic_{mode}.safetensors"));
        convert("convert", &pth, &file);
        let cfg = UNetConfig::preset(preset, Head::Segmentation { classes: 2 }).unwrap();
        let vs = VarStore::new(Device::Cpu);
        let net = UNet::new(&vs.root(), &cfg, &ConvKind::Standard, SIZE).unwrap();
        checkpoint::load(&file, &vs, &cfg).unwrap();
        let io = read_safetensors(&dir.path().join(format!("classic_{mode}_io.safetensors")));
        let y = tch::no_grad(|| net.f_forward_raw_t(&io["input"], false)).unwrap();
        let e = max_rel(&y, &io["output"]);
        eprintln!("torch -> calibconv, {preset}: max relative error {e:.3e}");
        assert!(e < TOL, "{preset}: {e}");
    }
}

#[test]
fn converted_pytorch_checkpoints_load_into_calibrated_networks_for_fine_tuning() {
    let dir = fixtures();
    for (mode, up) in MODES {
        let cfg = config(up);
        // A larger input: the F195 kernels need a few pixels at the deepest level.
        let vs = VarStore::new(Device::Cpu);
        let net = UNet::new(&vs.root(), &cfg, &f195(), [56, 64]).unwrap();
        checkpoint::load(&dir.join(format!("{mode}.safetensors")), &vs, &cfg).unwrap();
        let x = Tensor::rand([1, 3, 56, 64], (Kind::Float, Device::Cpu));
        let y = net.f_forward_t(&x, true).unwrap();
        assert_eq!(y.size(), [1, 3, 56, 64]);
        y.sum(Kind::Float).backward();
        assert_eq!(y.isfinite().all().int64_value(&[]), 1, "{mode}");
    }
}

#[test]
fn a_converted_checkpoint_for_another_architecture_lists_every_difference() {
    let dir = fixtures();
    let file = dir.join("transposed.safetensors");
    let cfg = UNetConfig {
        base: 16,
        up: UpMode::Bilinear,
        head: Head::Depth,
        ..config(UpMode::Transposed)
    };
    let vs = VarStore::new(Device::Cpu);
    UNet::new(&vs.root(), &cfg, &ConvKind::Standard, SIZE).unwrap();
    let err = checkpoint::load(&file, &vs, &cfg).unwrap_err().to_string();
    for part in [
        "transposed.safetensors",
        "up-sampling: transposed in the file, bilinear in the network",
        "classes: 3 in the file, 1 in the network (a depth network has 1)",
        "base: 8 in the file, 16 in the network",
    ] {
        assert!(err.contains(part), "{part}: {err}");
    }
}

/// A depth experiment on the toy task whose initial weights are `init`.
fn experiment(dir: &Path, name: &str, kernel: &str, up: &str, init: &Path) -> Experiment {
    ExperimentFile::tiny(name)
        .set("seed", 1)
        .set_path("output", dir)
        .set("model.kernel", kernel)
        .set("model.base", 8)
        .set("model.depth", 4)
        .set("model.up", up)
        .set_path("model.init.checkpoint", init)
        .square(64)
        .set_toml("data.train", r#"{ toy = 4, split = "train" }"#)
        .set("train.steps", 1)
        .set("train.log_every", 1)
        .load_in(dir)
}

#[test]
fn an_experiment_fine_tunes_a_converted_checkpoint_with_either_kernel_and_exports_it_back() {
    let dir = tempfile::tempdir().unwrap();
    let opts = quiet();
    for (mode, _) in MODES {
        let init = fixtures().join(format!("{mode}_1class.safetensors"));
        for kernel in ["standard", "calibrated"] {
            let exp = experiment(dir.path(), &format!("{mode}-{kernel}"), kernel, mode, &init);
            let out = experiment::train(&exp, &opts).unwrap();
            assert_eq!(out.summary.steps, 1, "{mode} {kernel}");
            let run = common::read_text(&exp.run_dir.join("run.json"));
            assert!(run.contains(&format!("{mode}_1class.safetensors")), "{run}");
            if kernel == "standard" {
                // Fine-tuned here, exported, and PyTorch computes the same as calibconv.
                let e = export_and_compare(
                    &train::last_path(&exp.run_dir.join("checkpoints")),
                    &exp.model,
                    [64, 64],
                    dir.path(),
                    &exp.name,
                );
                eprintln!("calibconv (trained) -> torch, {mode}: max relative error {e:.3e}");
                assert!(e < TOL, "{mode}: {e}");
            }
        }
    }
    // A 3-class segmentation checkpoint for a depth network: the architecture record says why.
    let init = fixtures().join("bilinear.safetensors");
    let exp = experiment(dir.path(), "wrong", "standard", "transposed", &init);
    let err = format!("{:#}", experiment::train(&exp, &opts).unwrap_err());
    assert!(
        err.contains("up-sampling: bilinear in the file, transposed"),
        "{err}"
    );
    assert!(
        err.contains("classes: 3 in the file, 1 in the network"),
        "{err}"
    );
}

/// Exports the calibconv checkpoint `ckpt` (a standard-kernel `cfg` network) with `calibconv
/// export` to `dir/STEM_state_dict.safetensors`, runs the same random input through it in
/// calibconv and, after a strict `load_state_dict`, in PyTorch (eval mode, raw `outc` output),
/// and returns the largest relative difference.
fn export_and_compare(
    ckpt: &Path,
    cfg: &UNetConfig,
    size: [i64; 2],
    dir: &Path,
    stem: &str,
) -> f64 {
    let vs = VarStore::new(Device::Cpu);
    let net = UNet::new(&vs.root(), cfg, &ConvKind::Standard, size).unwrap();
    checkpoint::load(ckpt, &vs, cfg).unwrap();
    let x = Tensor::rand(
        [2, cfg.in_channels, size[0], size[1]],
        (Kind::Float, Device::Cpu),
    );
    let y = tch::no_grad(|| net.f_forward_raw_t(&x, false)).unwrap();
    let (torch, _) = export_to_torch(ckpt, &x, dir, stem);
    max_rel(&y, &torch)
}

/// Exports `ckpt` with `calibconv export` to `dir/STEM_state_dict.safetensors`, loads that
/// strictly into PyTorch's network and returns its output for `x` (eval mode, raw `outc`
/// output) and the exported file.
fn export_to_torch(ckpt: &Path, x: &Tensor, dir: &Path, stem: &str) -> (Tensor, PathBuf) {
    let state = dir.join(format!("{stem}_state_dict.safetensors"));
    convert("export", ckpt, &state);
    let io = dir.join(format!("{stem}_io.safetensors"));
    Tensor::write_safetensors(&[("input", x)], &io).unwrap();
    let out = dir.join(format!("{stem}_torch.safetensors"));
    python(&[Path::new("rust-to-torch"), &state, &io, &out]);
    let mut torch = read_safetensors(&out);
    (torch.remove("output").expect("output in the result"), state)
}

fn randomise_batchnorm(vs: &VarStore) {
    tch::no_grad(|| {
        for (name, mut t) in vs.variables() {
            let (lo, hi) = if name.ends_with("running_var") {
                (0.5, 2.0)
            } else if name.ends_with("running_mean") {
                (-0.3, 0.3)
            } else if name.contains("double_conv.1.") || name.contains("double_conv.4.") {
                if name.ends_with("weight") {
                    (0.5, 1.5)
                } else {
                    (-0.2, 0.2)
                }
            } else {
                continue;
            };
            let _ = t.uniform_(lo, hi);
        }
    });
}

#[test]
fn exported_checkpoints_load_strictly_into_pytorch_and_give_the_same_outputs() {
    let dir = tempfile::tempdir().unwrap();
    for (mode, up) in MODES {
        let cfg = config(up);
        tch::manual_seed(11);
        let vs = VarStore::new(Device::Cpu);
        let net = UNet::new(&vs.root(), &cfg, &ConvKind::Standard, SIZE).unwrap();
        randomise_batchnorm(&vs);
        let ckpt = dir.path().join(format!("{mode}.safetensors"));
        let info = CheckpointInfo {
            experiment: Some("parity".into()),
            step: 3,
            batch_in_epoch: 3,
            ..common::checkpoint_info(cfg, SIZE)
        };
        checkpoint::save(&ckpt, &vs, &info).unwrap();
        let x = Tensor::rand([2, 3, SIZE[0], SIZE[1]], (Kind::Float, Device::Cpu));
        let y = tch::no_grad(|| net.f_forward_raw_t(&x, false)).unwrap();
        let (torch, state) = export_to_torch(&ckpt, &x, dir.path(), mode);
        let e = max_rel(&y, &torch);
        eprintln!("calibconv -> torch, {mode}: max relative error {e:.3e}");
        assert!(e < TOL, "{mode}: {e}");
        // milesial's key counts (depth 4), with the counters strict loading needs.
        let keys = read_safetensors(&state);
        let want = if up == UpMode::Transposed { 118 } else { 110 };
        assert_eq!(keys.len(), want, "{mode}");
        let n = &keys["down4.maxpool_conv.1.double_conv.4.num_batches_tracked"];
        assert_eq!((n.size(), n.kind()), (vec![], Kind::Int64));
        // And it loads back into calibconv: the same network.
        let vs2 = VarStore::new(Device::Cpu);
        let back = UNet::new(&vs2.root(), &cfg, &ConvKind::Standard, SIZE).unwrap();
        checkpoint::load(&state, &vs2, &cfg).unwrap();
        let y2 = tch::no_grad(|| back.f_forward_raw_t(&x, false)).unwrap();
        assert!(y2.equal(&y), "{mode}: export -> load round trip");
    }
}

#[test]
fn convert_and_export_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("w.safetensors");
    let out = out.to_str().unwrap();
    let err = failed(calibconv(&["convert", "no/such.pth", "--out", out]));
    assert!(err.contains("no/such.pth: no such file"), "{err}");
    let pth = fixtures().join("bilinear.pth");
    let args = ["convert", s(&pth), "--out", out, "--python", "no/python"];
    let err = failed(calibconv(&args));
    assert!(err.contains("no Python environment at no/python"), "{err}");
    // A converted PyTorch file has no calibconv metadata: nothing to export.
    let conv = fixtures().join("bilinear.safetensors");
    let err = failed(calibconv(&["export", s(&conv), "--out", out]));
    assert!(err.contains("not a calibconv checkpoint"), "{err}");
    assert!(!Path::new(out).exists());
}
