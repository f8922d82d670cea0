//! Training and evaluation on data set folders written by `calibconv synth` (the data module's
//! loader behind the experiment's data sources), and the geometry check between a data set's
//! camera and the experiment's input camera.

use std::path::{Path, PathBuf};

use calibconv::experiment::{self, Experiment};

use crate::common::experiment::{quiet, ExperimentFile};
use crate::common::{assert_contains, calibconv, ok, s};

fn camera(name: &str) -> String {
    format!("{}/data/cameras/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// F195 and Pers sets, 128 px wide (128x114 stored), 32 / 4 / 4 samples.
fn synth(dir: &Path) -> PathBuf {
    let root = dir.join("synth");
    let args = [
        "synth",
        "--out",
        s(&root),
        "--panoramas",
        "10",
        "--pano-height",
        "128",
    ];
    ok(calibconv(
        &[&args[..], &["--set", "f195", "--set", "pers"]].concat(),
    ));
    root
}

/// Trains on the F195 set's train split (validating on val) through `input_camera`, and
/// evaluates on F195's test split (calibrated kernels) and on the Pers set.
fn experiment(dir: &Path, data: &Path, input_camera: &str) -> ExperimentFile {
    let set = |name: &str, split: &str| {
        format!(
            "{{ dataset = \"{}\", split = \"{split}\" }}",
            data.join(name).display()
        )
    };
    let test = set("f195", "test");
    let pers = set("pers", "test");
    let pers_cam = camera("pers.toml");
    ExperimentFile::tiny("ds")
        .set_path("output", dir)
        .set("input.camera", camera(input_camera))
        // 1080x960 -> 1080x1080, scaled to 128x128: the stored 128x114 + 14 rows.
        .square(128)
        .set_toml("data.train", &set("f195", "train"))
        .set_toml("data.val", &set("f195", "val"))
        .set("train.steps", 4)
        .set("train.batch_size", 4)
        .set("train.images", 1)
        .eval(&format!(
            r#"{{ name = "f195-calibrated", data = {test}, kernel = "calibrated", images = 1 }}"#
        ))
        .eval(&format!(
            r#"{{ name = "pers-standard", data = {pers}, camera = "{pers_cam}", padding = [0, 120], size = [128, 128], images = 1 }}"#
        ))
}

/// Synthesises the data sets in `dir` and loads [`experiment`] through `input_camera`.
fn setup(dir: &Path, input_camera: &str) -> (PathBuf, Experiment) {
    let data = synth(dir);
    let exp = experiment(dir, &data, input_camera).load_in(dir);
    (data, exp)
}

#[test]
fn trains_and_evaluates_on_synthesised_data_sets() {
    let dir = tempfile::tempdir().unwrap();
    let (_, exp) = setup(dir.path(), "f195.toml");
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
    // F165 as the input camera, F195 images: the calibrated kernels would be for another lens.
    let (data, exp) = setup(dir.path(), "f165.toml");
    let e = experiment::train(&exp, &quiet()).unwrap_err().to_string();
    assert_contains(&e, &["f195", "is not the experiment's input camera"]);
    // An unknown split names the folder and the valid splits.
    let training = format!(
        "{{ dataset = \"{}\", split = \"training\" }}",
        data.join("f195").display()
    );
    let exp = experiment(dir.path(), &data, "f195.toml")
        .set_toml("data.train", &training)
        .set("name", "ds2")
        .load_in(dir.path());
    let e = experiment::train(&exp, &quiet()).unwrap_err().to_string();
    assert!(e.contains("unknown split `training`"), "{e}");
}
