//! The report of seed replicates end to end: run directories written the way evaluations write
//! them (`Evaluation::write` on in-memory test sets with known predictions), then
//! `write_report_with`: tables with intervals over seeds, paired differences with bootstrap
//! intervals, `verdict.json` / `verdict.md`; one replicate without seed folders; an unreadable
//! metrics file named in the error.

use std::path::{Path, PathBuf};

use serde_json::json;
use tch::{Device, Kind, Tensor};

use calibconv::data::memory::MemorySource;
use calibconv::eval::metrics::{Averaging, Metric, RadialBins};
use calibconv::eval::{evaluate_with, EvalOptions};
use calibconv::loss::DepthLoss;
use calibconv::nn::Head;
use calibconv::report::results::{write_report_with, ReportOptions};
use calibconv::report::verdict::{Outcome, Sign, Verdict};

use crate::common;

/// Test images per evaluation (1 x 8 pixels, ground truth 1 m).
const IMAGES: usize = 12;
const WIDTH: usize = 8;

/// Writes `eval/NAME/` of `run` for a depth predictor whose error at pixel `u` of image `i` is
/// `err(i, u)`.
fn write_eval(run: &Path, name: &str, kernel: &str, err: impl Fn(usize, usize) -> f64) {
    let pred: Vec<f32> = (0..IMAGES)
        .flat_map(|i| (0..WIDTH).map(move |u| (i, u)))
        .map(|(i, u)| (1.0 + err(i, u)) as f32)
        .collect();
    let pred = Tensor::from_slice(&pred).view([IMAGES as i64, 1, 1, WIDTH as i64]);
    let ids = (0..IMAGES).map(|i| format!("p{:03}_v0", i)).collect();
    let source = MemorySource::new(
        pred.repeat([1, 3, 1, 1]),
        pred.ones_like(),
        Tensor::zeros([IMAGES as i64, 1, WIDTH as i64], (Kind::Int64, Device::Cpu)),
        pred.ones_like().to_kind(Kind::Bool),
        ids,
        4,
        None,
    )
    .unwrap();
    let opts = EvalOptions {
        bins: RadialBins::new([0.0, 0.0], [1, WIDTH as i64], 4, None).unwrap(),
        panels: 0,
        depth_loss: DepthLoss::L1,
        device: Device::Cpu,
        progress: false,
    };
    let e = evaluate_with(Head::Depth, &source, &opts, |x| Ok(x.narrow(1, 0, 1))).unwrap();
    e.write(
        &run.join("eval").join(name),
        &json!({"experiment": "x", "evaluation": name, "kernel": kernel,
                "camera_file": camera_file(name)}),
    )
    .unwrap();
}

/// The camera file an evaluation `SET-KERNEL` names, as the experiment layer writes it.
fn camera_file(name: &str) -> String {
    let set = name.split('-').next().unwrap();
    format!("{}/data/cameras/{set}.toml", env!("CARGO_MANIFEST_DIR"))
}

/// One seed's BL and two FT runs on F195: BL calibrated worse than standard, FT calibrated
/// better (errors smaller by `gain`, larger outward), with a seed-dependent offset.
fn write_seed(dir: &Path, seed: u64, gain: f64) {
    let root = env!("CARGO_MANIFEST_DIR");
    let copy = |file: &str, name: &str| {
        let run = dir.join(name);
        std::fs::create_dir_all(&run).unwrap();
        std::fs::copy(
            Path::new(root).join("experiments/paper").join(file),
            run.join("experiment.toml"),
        )
        .unwrap();
        run
    };
    let s = seed as f64 * 0.01;
    let base = move |i: usize, u: usize| 0.2 + 0.02 * i as f64 + 0.01 * u as f64 + s;
    let bl = copy("depth-bl-pers.toml", "paper-depth-bl-pers");
    write_eval(&bl, "f195-standard", "standard", base);
    write_eval(&bl, "f195-calibrated", "calibrated", move |i, u| {
        base(i, u) + 0.05
    });
    let ft = copy(
        "depth-ft-f195-standard.toml",
        "paper-depth-ft-f195-standard",
    );
    write_eval(&ft, "f195-standard", "standard", base);
    let ft = copy(
        "depth-ft-f195-calibrated.toml",
        "paper-depth-ft-f195-calibrated",
    );
    write_eval(&ft, "f195-calibrated", "calibrated", move |i, u| {
        base(i, u) - gain * (1.0 + u as f64 / WIDTH as f64)
    });
}

/// A temporary folder and the results folder to write in it (not made yet).
fn results_dir() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let results = tmp.path().join("results");
    (tmp, results)
}

fn read_verdict(dir: &Path) -> Verdict {
    serde_json::from_str(&std::fs::read_to_string(dir.join("verdict.json")).unwrap()).unwrap()
}

/// The text of the report file `name` in `dir`, after checking that it contains every one of
/// `parts`.
#[track_caller]
fn report_has(dir: &Path, name: &str, parts: &[&str]) -> String {
    common::file_containing(&dir.join(name), parts)
}

#[test]
fn three_seeds_give_intervals_differences_and_a_verdict() {
    let (tmp, results) = results_dir();
    for (seed, gain) in [(0, 0.10), (1, 0.12), (2, 0.08)] {
        write_seed(&results.join(format!("seed-{seed}")), seed, gain);
    }
    let files = write_report_with(&results, &results, &ReportOptions::default()).unwrap();
    for f in [
        "table_depth.md",
        "differences_depth.csv",
        "verdict.json",
        "verdict.md",
    ] {
        assert!(files.iter().any(|p| p.ends_with(f)), "{f} not written");
    }
    report_has(
        &results,
        "table_depth.md",
        &[
            "`per-image` averaging",
            "| FT | F195 | calibrated | 3 | ",
            " ± ",
        ],
    );
    report_has(
        &results,
        "differences_depth.md",
        &["| FT | F195 | calibrated − standard | rmse | 3 |", "s0: -"],
    );

    let v = read_verdict(&results);
    assert_eq!(v.seeds, [0, 1, 2]);
    assert_eq!(v.test_images, IMAGES as u64);
    assert_eq!(v.averaging, Averaging::PerImage);
    let row = |id: &str, m: Metric, compare: &str| {
        v.claims
            .iter()
            .find(|c| c.id == id && c.metric == m && c.compare.contains(compare))
            .unwrap_or_else(|| panic!("no {id} {m} {compare}"))
    };
    // C1: RMSE of calibrated lower in every seed: holds, sign negative.
    let c1 = row("C1", Metric::Rmse, "F195");
    assert_eq!(
        (c1.expected, c1.outcome),
        (Sign::Negative, Outcome::Holds),
        "{c1:?}"
    );
    assert_eq!(c1.per_seed.len(), 3);
    assert!(c1.per_seed.iter().all(|d| *d < 0.0));
    let [lo, hi] = c1.ci95.unwrap();
    assert!((hi - lo) / 2.0 - c1.half_width.unwrap() < 1e-12);
    // C5: BL calibrated worse (errors + 0.05 everywhere): holds with a positive RMSE sign.
    let c5 = row("C5", Metric::Rmse, "BL F195");
    assert_eq!((c5.expected, c5.outcome), (Sign::Positive, Outcome::Holds));
    // C6: the gain grows outward (larger error reduction at larger u).
    let c6 = row("C6", Metric::Rmse, "F195");
    assert_eq!(c6.outcome, Outcome::Holds, "{c6:?}");
    // F165 rows do not exist: inconclusive, saying which rows are missing.
    let c2 = row("C2", Metric::Rmse, "F165");
    assert_eq!(c2.outcome, Outcome::Inconclusive);
    assert!(c2.reason.as_ref().unwrap().contains("FT F165"));
    report_has(
        &results,
        "verdict.md",
        &["| C1 | depth | rmse | FT F195 calibrated - FT F195 standard | < 0 |"],
    );

    // Pooled averaging is a choice the tables state.
    let out = tmp.path().join("pooled");
    let opts = ReportOptions {
        averaging: Averaging::Pooled,
        ..Default::default()
    };
    write_report_with(&results, &out, &opts).unwrap();
    assert_eq!(read_verdict(&out).averaging, Averaging::Pooled);
    report_has(&out, "table_depth.md", &["`pooled` averaging"]);
}

#[test]
fn one_replicate_without_seed_folders_prints_no_interval() {
    let (_tmp, results) = results_dir();
    write_seed(&results, 0, 0.1);
    write_report_with(&results, &results, &ReportOptions::default()).unwrap();
    let table = report_has(&results, "table_depth.md", &["need >= 2 seeds"]);
    assert!(!table.contains('±'), "{table}");
    let diffs = report_has(&results, "differences_depth.md", &["needs >= 2 seeds"]);
    assert!(!diffs.contains('['), "{diffs}");
    let v = read_verdict(&results);
    // The experiment files' own seed.
    assert_eq!(v.seeds, [0]);
    for c in &v.claims {
        assert_eq!(c.outcome, Outcome::Inconclusive);
        assert!(c.ci95.is_none() && c.half_width.is_none());
        assert!(c.reason.is_some(), "{c:?}");
    }
    report_has(
        &results,
        "verdict.md",
        &["an interval over seeds needs >= 2 seeds"],
    );
}

#[test]
fn an_unreadable_metrics_file_is_an_error_naming_it() {
    let (_tmp, results) = results_dir();
    write_seed(&results.join("seed-0"), 0, 0.1);
    write_seed(&results.join("seed-1"), 1, 0.1);
    let bad = results.join("seed-1/paper-depth-ft-f195-standard/eval/f195-standard/metrics.json");
    std::fs::write(&bad, "{\"task\": \"depth\"").unwrap();
    let e = write_report_with(&results, &results, &ReportOptions::default()).unwrap_err();
    assert!(e.to_string().contains(&bad.display().to_string()), "{e}");
    // A missing per-image file (needed for the bootstrap) too.
    write_seed(&results.join("seed-1"), 1, 0.1);
    let per = bad.with_file_name("per_image.json");
    std::fs::remove_file(&per).unwrap();
    let e = write_report_with(&results, &results, &ReportOptions::default()).unwrap_err();
    assert!(e.to_string().contains(&per.display().to_string()), "{e}");
}

#[test]
fn a_shared_baseline_leaves_c5_without_an_interval() {
    // share_baseline: the BL run lives in the first seed's folder only.
    let (_tmp, results) = results_dir();
    for (seed, gain) in [(0, 0.10), (1, 0.12), (2, 0.08)] {
        write_seed(&results.join(format!("seed-{seed}")), seed, gain);
        if seed > 0 {
            let bl = results.join(format!("seed-{seed}/paper-depth-bl-pers"));
            std::fs::remove_dir_all(bl).unwrap();
        }
    }
    let study = calibconv::experiment::layout::StudyRecord {
        dir: "experiments/paper".into(),
        overlay: calibconv::experiment::layout::Overlay {
            profile: "quick".into(),
            ..Default::default()
        },
        seeds: vec![0, 1, 2],
        share_baseline: true,
        git: None,
        runs: vec![],
    };
    calibconv::experiment::layout::write_record(&results.join("study.json"), &study).unwrap();
    write_report_with(&results, &results, &ReportOptions::default()).unwrap();
    let v = read_verdict(&results);
    assert_eq!(v.profile, "quick");
    let c5 = v
        .claims
        .iter()
        .find(|c| c.id == "C5" && c.metric == Metric::Rmse && c.compare.contains("F195"))
        .unwrap();
    assert_eq!((c5.per_seed.len(), c5.outcome), (1, Outcome::Inconclusive));
    assert!(c5.reason.as_ref().unwrap().contains(">= 2 seeds"), "{c5:?}");
    // The FT claims still have three seeds.
    let c1 = v.claims.iter().find(|c| c.id == "C1").unwrap();
    assert_eq!((c1.per_seed.len(), c1.outcome), (3, Outcome::Holds));
    report_has(&results, "verdict.md", &["share_baseline"]);
    report_has(
        &results,
        "table_depth.md",
        &["| BL (Pers) | F195 | standard | 1 | "],
    );
}

#[test]
fn the_gain_against_the_field_of_view_has_one_point_per_lens() {
    let (_tmp, results) = results_dir();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (seed, gain) in [(0u64, 0.10), (1, 0.12), (2, 0.08)] {
        let dir = results.join(format!("seed-{seed}"));
        write_seed(&dir, seed, gain);
        // F165 fine-tunings: calibrated better by half the F195 gain.
        for kernel in ["standard", "calibrated"] {
            let name = format!("paper-depth-ft-f165-{kernel}");
            let run = dir.join(&name);
            std::fs::create_dir_all(&run).unwrap();
            std::fs::copy(
                root.join(format!("experiments/paper/depth-ft-f165-{kernel}.toml")),
                run.join("experiment.toml"),
            )
            .unwrap();
            let g = if kernel == "calibrated" {
                gain / 2.0
            } else {
                0.0
            };
            write_eval(&run, &format!("f165-{kernel}"), kernel, move |i, u| {
                0.2 + 0.02 * i as f64 + 0.01 * u as f64 - g
            });
        }
    }
    write_report_with(&results, &results, &ReportOptions::default()).unwrap();
    let rows: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(results.join("fov_gain.json")).unwrap())
            .unwrap();
    let rmse: Vec<&serde_json::Value> = rows
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["metric"] == "rmse")
        .collect();
    // F165 then F195 (by field of view), three seeds each, both gains negative (better).
    assert_eq!(rmse.len(), 2, "{rows}");
    assert_eq!(
        (rmse[0]["fov_deg"].as_f64(), rmse[1]["fov_deg"].as_f64()),
        (Some(165.0), Some(195.0))
    );
    for r in &rmse {
        assert_eq!(r["n_seeds"], 3);
        assert!(r["mean"].as_f64().unwrap() < 0.0, "{r}");
        assert!(r["ci95"][1].as_f64().unwrap() < 0.0, "{r}");
    }
    assert!(rmse[1]["mean"].as_f64().unwrap() < rmse[0]["mean"].as_f64().unwrap());
    assert!(results.join("fov_gain.png").is_file());
    report_has(
        &results,
        "REPORT.md",
        &["## Gain against the field of view"],
    );
}

/// `calibconv report` on a trained fine-tuned calibrated depth run draws its point cloud (the
/// top view, and the PLY files unless `--no-ply`, which also removes those of an earlier report).
#[test]
fn the_command_draws_a_point_cloud_and_no_ply_leaves_the_files_out() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let runs = dir.join("runs");
    let file = dir.join("t.toml");
    common::experiment::ExperimentFile::tiny("t-depth-ft-f195-calibrated")
        .set_path("output", &runs)
        .set("model.kernel", "calibrated")
        .square(32)
        .set("train.steps", 1)
        .set_toml("data.train", r#"{ toy = 4, split = "train" }"#)
        .eval(r#"{ name = "f195-calibrated", data = { toy = 2, split = "test" } }"#)
        .write(&file);
    common::ok(common::calibconv_in(
        dir,
        &["train", "-q", common::s(&file)],
    ));
    let out = dir.join("out");
    let report = |extra: &[&str]| {
        let mut args = vec!["report", "runs", "--out", "out"];
        args.extend_from_slice(extra);
        common::ok(common::calibconv_in(dir, &args))
    };
    report(&[]);
    let md = |out: &Path| std::fs::read_to_string(out.join("REPORT.md")).unwrap();
    for f in [
        "pointcloud_pred.ply",
        "pointcloud_true.ply",
        "pointcloud_top.png",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    assert!(md(&out).contains("[predicted](pointcloud_pred.ply)"));
    let o = report(&["--no-ply"]);
    assert!(
        common::stdout(&o).contains("removed"),
        "{}",
        common::stdout(&o)
    );
    assert!(!out.join("pointcloud_pred.ply").exists() && !out.join("pointcloud_true.ply").exists());
    assert!(out.join("pointcloud_top.png").is_file());
    let text = md(&out);
    assert!(
        text.contains("## Point cloud") && !text.contains(".ply"),
        "{text}"
    );
}
