use std::path::Path;

use tch::Device;

use super::*;
use crate::eval::metrics::Metric;
use crate::loss::DepthLoss;
use crate::nn::{Head, UNetConfig};
use crate::train::schedule::Schedule;
use crate::train::Length;

const CAM: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/cameras/f195.toml");
const PERS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/cameras/pers.toml");

fn base() -> String {
    format!(
        r#"
name = "t"
task = "depth"

[model]
preset = "tiny"
kernel = "calibrated"

[input]
camera = "{CAM}"
size = [60, 68]

[data]
train = {{ toy = 8, split = "train" }}
val = {{ toy = 4, split = "val" }}
test = {{ toy = 4, split = "test" }}

[train]
steps = 10
batch_size = 2

[optimizer]
lr = 1e-3
"#
    )
}

fn resolve(text: &str) -> Result<Experiment> {
    let path = Path::new("x.toml");
    parse(text, path)?.resolve(path, text)
}

fn err(text: &str) -> String {
    resolve(text).unwrap_err().to_string()
}

#[test]
fn defaults_are_filled_in() {
    let e = resolve(&base()).unwrap();
    assert_eq!(e.model, UNetConfig::preset("tiny", Head::Depth).unwrap());
    assert_eq!(e.input.size, [60, 68]);
    assert_eq!(e.input.padding, [0, 0]);
    assert_eq!(e.train.length, Length::Steps(10));
    assert_eq!(e.train.val_metric, Metric::Rmse);
    assert_eq!(e.train.depth_loss, DepthLoss::L1);
    assert_eq!(e.train.schedule, Schedule::constant(1e-3));
    assert_eq!(e.seed, 0);
    assert!(e.run_dir.ends_with("runs/t"));
    // No [[eval]]: one evaluation of the test split with the model's kernel.
    assert_eq!(e.evals.len(), 1);
    assert_eq!(e.evals[0].name, "test");
    assert_eq!(e.evals[0].kernel, KernelName::Calibrated);
    assert_eq!(e.evals[0].input.size, [60, 68]);
    // Without a size, the input is the camera image plus padding.
    let e = resolve(&base().replace("size = [60, 68]", "padding = [8, 0]")).unwrap();
    assert_eq!(e.input.size, [960, 1088]);
}

#[test]
fn unknown_keys_and_values_name_the_key_and_suggest_the_nearest() {
    // (text replaced, its replacement, what the error must say)
    let cases: [(&str, &str, &[&str]); 6] = [
        (
            "lr = 1e-3",
            "lr = 1e-3\nweigth_decay = 0.1",
            &["`optimizer.weigth_decay`", "did you mean `weight_decay`"],
        ),
        (
            "batch_size = 2",
            "batchsize = 2",
            &["`train.batchsize`", "did you mean `batch_size`"],
        ),
        (
            "kernel = \"calibrated\"",
            "kernel = \"calibated\"",
            &["did you mean `calibrated`"],
        ),
        (
            "preset = \"tiny\"",
            "preset = \"tinny\"",
            &["model.preset", "did you mean `tiny`"],
        ),
        (
            "task = \"depth\"",
            "task = \"depth\"\nsed = 3",
            &["did you mean `seed`"],
        ),
        (
            "batch_size = 2",
            "batch_size = 2\nval_metric = \"miou\"",
            &["train.val_metric", "`miou` is not one of"],
        ),
    ];
    for (from, to, wants) in cases {
        let e = err(&base().replace(from, to));
        for want in wants {
            assert!(e.contains(want), "{want}: {e}");
        }
    }
}

#[test]
fn inconsistent_values_are_errors_naming_the_field() {
    let cases = [
        ("steps = 10", "steps = 10\nepochs = 2", "`train`"),
        (
            "{ toy = 8, split = \"train\" }",
            "{ toy = 8, dataset = \"d\", split = \"train\" }",
            "data.train",
        ),
        ("lr = 1e-3", "lr = -1.0", "optimizer.lr"),
        (
            "kernel = \"calibrated\"",
            "kernel = \"calibrated\"\nclasses = 4",
            "model.classes",
        ),
        (
            "batch_size = 2",
            "batch_size = 2\nloss = \"cross-entropy\"",
            "train.loss",
        ),
        ("name = \"t\"", "name = \"a/b\"", "`name`"),
        // A 16x16 input leaves 2 px at the deepest level: too narrow for 195 deg kernels.
        ("size = [60, 68]", "size = [16, 16]", "input.size"),
        (
            "[optimizer]",
            "[schedule]\nkind = \"step\"\n\n[optimizer]",
            "schedule.every",
        ),
        (
            "[optimizer]",
            "[schedule]\nkind = \"constant\"\nmin_lr = 0.1\n\n[optimizer]",
            "schedule.min_lr",
        ),
        (
            "kernel = \"calibrated\"",
            "kernel = \"calibrated\"\ninit = { experiment = \"t\" }",
            "model.init.experiment",
        ),
    ];
    for (from, to, field) in cases {
        let text = base().replace(from, to);
        assert_ne!(text, base(), "{from}");
        let e = err(&text);
        assert!(e.contains(field), "{to}: {e}");
    }
    let e = err(&base().replace(CAM, "/nonexistent/cam.toml"));
    assert!(
        e.contains("input.camera") && e.contains("/nonexistent/cam.toml"),
        "{e}"
    );
}

#[test]
fn evaluations_inherit_and_override_the_input() {
    let text = base()
        + &format!(
            r#"
[[eval]]
name = "same"
data = {{ toy = 4, split = "test" }}
kernel = "standard"

[[eval]]
name = "pers"
data = {{ toy = 4, split = "test" }}
camera = "{PERS}"
size = [48, 64]
radial_bins = 5
"#
        );
    let e = resolve(&text).unwrap();
    assert_eq!(e.evals.len(), 2);
    assert_eq!(e.evals[0].kernel, KernelName::Standard);
    assert_eq!(e.evals[0].input.size, [60, 68]);
    assert_eq!(e.evals[1].kernel, KernelName::Calibrated);
    assert_eq!(e.evals[1].input.size, [48, 64]);
    assert!(e.evals[1].input.camera_file.ends_with("pers.toml"));
    assert_eq!(e.evals[1].radial_bins, 5);
    let dup = text.replace("name = \"pers\"", "name = \"same\"");
    assert!(err(&dup).contains("used twice"));
}

#[test]
fn init_by_experiment_name_points_at_its_checkpoints() {
    let text = base().replace(
        "kernel = \"calibrated\"",
        "kernel = \"calibrated\"\ninit = { experiment = \"bl\" }",
    );
    let e = resolve(&text).unwrap();
    match e.init {
        Some(InitSpec::Experiment { name, checkpoints }) => {
            assert_eq!(name, "bl");
            assert!(checkpoints.ends_with("runs/bl/checkpoints"));
        }
        other => panic!("{other:?}"),
    }
    // Not trained yet: a clear error at run time.
    let dir = tempfile::tempdir().unwrap();
    let text = text.replace(
        "task = \"depth\"",
        &format!("task = \"depth\"\noutput = \"{}\"", dir.path().display()),
    );
    let e = resolve(&text).unwrap();
    let err = run::init_checkpoint(&e).unwrap_err().to_string();
    assert!(
        err.contains("has no checkpoint") && err.contains("train it first"),
        "{err}"
    );
}

#[test]
fn devices_parse() {
    assert_eq!(parse_device("cpu").unwrap(), Device::Cpu);
    assert_eq!(parse_device("cuda:1").unwrap(), Device::Cuda(1));
    assert!(parse_device("gpu").is_err());
}
