//! Training and evaluation on data set folders written by `calibconv synth` (the data module's
//! loader behind the experiment's data sources), and the geometry check between a data set's
//! camera and the experiment's input camera.

mod common;

use calibconv::experiment::{self, DefaultOpener, RunOptions};
use common::calibconv;
use std::path::Path;

fn camera(name: &str) -> String {
    format!("{}/data/cameras/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// F195 and Pers sets, 128 px wide (128x114 stored), 32 / 4 / 4 samples.
fn synth(dir: &Path) -> std::path::PathBuf {
    let root = dir.join("synth");
    let o = calibconv(&[
        "synth",
        "--out",
        root.to_str().unwrap(),
        "--panoramas",
        "10",
        "--pano-height",
        "128",
        "--set",
        "f195",
        "--set",
        "pers",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    root
}

fn experiment_text(dir: &Path, data: &Path, input_camera: &str) -> String {
    let set = |name: &str, split: &str| {
        format!(
            "{{ dataset = \"{}\", split = \"{split}\" }}",
            data.join(name).display()
        )
    };
    format!(
        r#"
name = "ds"
task = "depth"
output = "{out}"
device = "cpu"

[model]
preset = "tiny"
kernel = "standard"

[input]
camera = "{cam}"
padding = [0, 120]     # 1080x960 -> 1080x1080, scaled to 128x128: the stored 128x114 + 14 rows
size = [128, 128]

[data]
train = {train}
val = {val}

[train]
steps = 4
batch_size = 4
images = 1

[optimizer]
lr = 1e-3

[[eval]]
name = "f195-calibrated"
data = {test}
kernel = "calibrated"
images = 1

[[eval]]
name = "pers-standard"
data = {pers}
camera = "{pers_cam}"
padding = [0, 120]
size = [128, 128]
images = 1
"#,
        out = dir.display(),
        cam = camera(input_camera),
        train = set("f195", "train"),
        val = set("f195", "val"),
        test = set("f195", "test"),
        pers = set("pers", "test"),
        pers_cam = camera("pers.toml"),
    )
}

fn quiet() -> RunOptions<'static> {
    RunOptions {
        resume: false,
        progress: false,
        verbose: false,
        opener: &DefaultOpener,
    }
}

#[test]
fn trains_and_evaluates_on_synthesised_data_sets() {
    let dir = tempfile::tempdir().unwrap();
    let data = synth(dir.path());
    let file = dir.path().join("ds.toml");
    std::fs::write(&file, experiment_text(dir.path(), &data, "f195.toml")).unwrap();
    let exp = experiment::load(&file).unwrap();
    let out = experiment::train(&exp, &quiet()).unwrap();
    assert_eq!(out.summary.steps, 4);
    assert_eq!(out.evaluations.len(), 2);
    for e in &out.evaluations {
        assert_eq!(e.evaluation.images, 4, "{}", e.name);
        assert!(e.evaluation.pixels > 0, "{}", e.name);
        assert!(e.dir.join("metrics.json").is_file());
    }
    let csv = std::fs::read_to_string(exp.run_dir.join("evaluations.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3, "{csv}");
}

#[test]
fn a_data_set_of_another_camera_or_split_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let data = synth(dir.path());
    // F165 as the input camera, F195 images: the calibrated kernels would be for another lens.
    let file = dir.path().join("ds.toml");
    std::fs::write(&file, experiment_text(dir.path(), &data, "f165.toml")).unwrap();
    let exp = experiment::load(&file).unwrap();
    let e = experiment::train(&exp, &quiet()).unwrap_err().to_string();
    assert!(
        e.contains("f195") && e.contains("is not the experiment's input camera"),
        "{e}"
    );
    // An unknown split names the folder and the valid splits.
    let text = experiment_text(dir.path(), &data, "f195.toml")
        .replace("split = \"train\"", "split = \"training\"")
        .replace("name = \"ds\"", "name = \"ds2\"");
    std::fs::write(&file, text).unwrap();
    let exp = experiment::load(&file).unwrap();
    let e = experiment::train(&exp, &quiet()).unwrap_err().to_string();
    assert!(e.contains("unknown split `training`"), "{e}");
}
