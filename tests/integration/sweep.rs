//! Sweeps on tiny toy experiments: dependency order, skipping complete runs, a failed run that
//! does not stop the others (and blocks its dependants), overrides recorded in each run; the
//! SLURM scripts' structure; the report of the results.

use std::path::Path;

use calibconv::experiment::layout::{RunDir, SweepStatus};
use calibconv::experiment::profile::Override;
use calibconv::experiment::status;
use calibconv::experiment::sweep::{self, Outcome, State, SweepOptions};
use calibconv::experiment::DefaultOpener;
use calibconv::train::stop::StopFlag;

use crate::common::experiment::ExperimentFile;
use crate::common::{
    self, assert_contains, calibconv_in, failed, file_containing, ok, synth_tiny_f195,
};

/// A tiny toy experiment: 5 epochs of the tiny U-Net on 16x16 toy images, training on
/// `train`, fine-tuning `init` if given.
fn toy(name: &str, init: Option<&str>, train: &str) -> ExperimentFile {
    let e = ExperimentFile::tiny(name)
        .remove("train.steps")
        .set("train.epochs", 5)
        .set_toml("data.train", train)
        .set_toml("data.val", r#"{ toy = 4, split = "val" }"#)
        .eval(r#"{ name = "f195-standard", data = { toy = 4, split = "test" } }"#);
    match init {
        Some(i) => e.set_toml("model.init", &format!(r#"{{ experiment = "{i}" }}"#)),
        None => e,
    }
}

/// The toy experiments `bl`, `ft` (from `bl`), `broken` (its data set is missing) and
/// `after-broken` (from `broken`) in `dir`, with their data sets and runs under `dir`, and the
/// profile `tiny`.
fn write_set(dir: &Path) {
    let ok = r#"{ toy = 4, split = "train" }"#;
    let missing = r#"{ dataset = "no-such-folder", split = "train" }"#;
    for (name, init, train) in [
        ("bl", None, ok),
        ("ft", Some("bl"), ok),
        ("broken", None, missing),
        ("after-broken", Some("broken"), ok),
    ] {
        toy(name, init, train)
            .set_path("data_root", dir)
            .set_path("output", &dir.join("runs"))
            .write(&dir.join(format!("{name}.toml")));
    }
    std::fs::create_dir_all(dir.join("profiles")).unwrap();
    std::fs::write(
        dir.join("profiles/tiny.toml"),
        "[all]\ntrain = { steps = 2 }\n[finetune]\noptimizer = { lr = 5e-4 }\n",
    )
    .unwrap();
}

#[test]
fn sweeps_run_in_dependency_order_skip_complete_runs_and_go_past_failures() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_set(dir);
    let profile = sweep::find_profile(dir, "tiny").unwrap();
    let overrides: Vec<Override> = vec!["train.batch_size=1".parse().unwrap()];
    let plan = sweep::plan(dir, &profile, &overrides, &[]).unwrap();
    let order: Vec<(&str, usize)> = plan
        .iter()
        .map(|p| (p.exp.name.as_str(), p.level))
        .collect();
    assert_eq!(
        order,
        [("bl", 0), ("broken", 0), ("after-broken", 1), ("ft", 1)]
    );
    assert_eq!(plan[3].exp.train.batch_size, 1);
    let opts = SweepOptions {
        profile: &profile,
        overrides: &overrides,
        jobs: 2,
        progress: false,
        opener: &DefaultOpener,
        stop: StopFlag::detached(),
    };
    let out = sweep::run_sweep(&plan, &opts);
    let by = |n: &str| out.iter().find(|(m, _)| m == n).unwrap().1.clone();
    assert!(
        matches!(
            by("bl"),
            Outcome::Done {
                action: "train",
                ..
            }
        ),
        "{out:?}"
    );
    assert!(
        matches!(
            by("ft"),
            Outcome::Done {
                action: "train",
                ..
            }
        ),
        "{out:?}"
    );
    match by("broken") {
        Outcome::Failed(e) => assert!(e.contains("no-such-folder"), "{e}"),
        o => panic!("{o:?}"),
    }
    assert!(matches!(by("after-broken"), Outcome::Blocked(_)), "{out:?}");
    // Each run records what produced it.
    let rec = RunDir::new(dir.join("runs/ft")).read_sweep().unwrap();
    assert_eq!(rec.overlay.profile, "tiny");
    assert_eq!(rec.overlay.overrides, ["train.batch_size=1"]);
    assert_eq!(rec.depends_on, ["bl"]);
    assert_eq!(rec.status, SweepStatus::Done);
    assert!(rec.experiment_text.contains("steps = 2"));
    // The summary records where the time went.
    let summary = RunDir::new(dir.join("runs/ft")).read_summary().unwrap();
    assert!(summary.timing.steps > 0.0 && summary.timing.evaluation.is_some());
    let stored = std::fs::read_to_string(dir.join("runs/ft/experiment.toml")).unwrap();
    assert!(
        stored.contains("lr = 0.0005") && stored.contains("batch_size = 1"),
        "{stored}"
    );
    assert!(dir.join("runs/ft/config.json").is_file() && dir.join("runs/ft/run.json").is_file());

    // Again: complete runs are skipped; a run with evaluations missing is only evaluated.
    std::fs::remove_dir_all(dir.join("runs/ft/eval")).unwrap();
    assert_eq!(sweep::state(&plan[3].exp).unwrap(), State::Trained);
    let out = sweep::run_sweep(&plan, &opts);
    assert_eq!(out[0].1, Outcome::Skipped);
    assert!(
        matches!(
            out[3].1,
            Outcome::Done {
                action: "evaluate",
                ..
            }
        ),
        "{out:?}"
    );
    assert_eq!(sweep::state(&plan[3].exp).unwrap(), State::Complete);

    // The status table from these records: a row per run, failures with their first line.
    let rows = status::status(&plan);
    let states: Vec<String> = rows.iter().map(|r| r.state.describe(r.steps)).collect();
    assert_eq!(states[0], "complete");
    assert!(
        states[1].starts_with("failed: ") && states[1].contains("no-such-folder"),
        "{states:?}"
    );
    // Blocked before it had a folder: nothing on disk says more than that it never started.
    assert_eq!(states[2], "not started");
    assert_eq!(states[3], "complete");
    // The profile's 2 steps, done.
    assert_eq!((rows[3].steps, rows[3].total), (Some(2), Some(2)));

    // A stop requested before the sweep: complete runs are still skipped, no other run starts.
    let stop = StopFlag::detached();
    stop.request(libc::SIGTERM);
    let out = sweep::run_sweep(&plan, &SweepOptions { stop, ..opts });
    assert_eq!(out[0].1, Outcome::Skipped);
    match &out[1].1 {
        Outcome::Interrupted(e) => assert!(e.contains("not started: SIGTERM"), "{e}"),
        o => panic!("{o:?}"),
    }

    // Another configuration in the same run directory is refused, not overwritten.
    let other: Vec<Override> = vec!["optimizer.lr=0.1".parse().unwrap()];
    let plan2 = sweep::plan(dir, &profile, &other, &["bl".into()]).unwrap();
    assert_eq!(plan2.len(), 1);
    let out = sweep::run_sweep(
        &plan2,
        &SweepOptions {
            overrides: &other,
            ..opts
        },
    );
    match &out[0].1 {
        Outcome::Failed(e) => assert!(e.contains("another configuration"), "{e}"),
        o => panic!("{o:?}"),
    }

    // The report of these results: tables in REPORT.md, each run in runs.md.
    let files =
        calibconv::report::results::write_report(&dir.join("runs"), &dir.join("report")).unwrap();
    assert!(files.iter().any(|f| f.ends_with("table_depth.md")));
    let table = file_containing(
        &dir.join("report/table_depth.csv"),
        &["BL,F195,standard,1,", "FT,F195,standard,1,"],
    );
    assert!(
        table.starts_with("block,dataset,kernel,n,mre,mre_ci95_half_width,mae,"),
        "{table}"
    );
    file_containing(
        &dir.join("report/REPORT.md"),
        &["| FT | F195 | standard | 1 |"],
    );
    file_containing(&dir.join("report/runs.md"), &["[ft](../runs/ft)"]);
    assert!(dir.join("report/verdict.json").is_file());
}

#[test]
fn the_command_exits_non_zero_after_a_failure_and_writes_slurm_scripts_by_level() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_set(dir);
    let d = dir.display().to_string();
    let sweep = |extra: &[&str]| {
        let args = ["sweep", d.as_str(), "--profile", "tiny"];
        calibconv_in(dir, &[&args[..], extra].concat())
    };
    let text = failed(sweep(&["--only", "*broken", "-q"]));
    assert_contains(&text, &["FAILED broken", "BLOCKED after-broken"]);

    let slurm = dir.join("slurm");
    ok(sweep(&[
        "--set",
        "optimizer.lr=1e-4",
        "--emit-slurm",
        common::s(&slurm),
    ]));
    let l0 = file_containing(
        &slurm.join("level-0.sbatch"),
        &["#SBATCH --array=0-1\n", "RUNS=(bl broken)\n"],
    );
    assert!(l0.starts_with("#!/bin/bash\n"));
    file_containing(
        &slurm.join("level-1.sbatch"),
        &[
            "#SBATCH --array=0-1\n",
            "RUNS=(after-broken ft)\n",
            "--profile",
            "--set 'optimizer.lr=0.0001'",
            "--only \"${RUNS[$SLURM_ARRAY_TASK_ID]}\"",
        ],
    );
    let submit = std::fs::read_to_string(slurm.join("submit.sh")).unwrap();
    let lines: Vec<&str> = submit.lines().filter(|l| l.contains("sbatch")).collect();
    assert_eq!(
        lines,
        [
            "j0=$(sbatch --parsable level-0.sbatch)",
            "j1=$(sbatch --parsable --dependency=afterok:$j0 level-1.sbatch)"
        ]
    );
}

#[test]
fn experiments_train_on_data_set_folders_and_refuse_another_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    synth_tiny_f195(&dir.join("sets"), 16);
    let set = |split: &str| format!(r#"{{ dataset = "f195", split = "{split}" }}"#);
    let exp = |eval_camera: &str| {
        let camera = common::root().join(format!("data/cameras/{eval_camera}.toml"));
        let eval = format!(
            r#"{{ name = "f195-standard", data = {}, camera = "{}" }}"#,
            set("test"),
            camera.display()
        );
        ExperimentFile::tiny("ds")
            .set_path("data_root", &dir.join("sets"))
            .set_path("output", &dir.join("runs"))
            .remove("input.size")
            .set("input.width", 16)
            .set("input.padding", vec![0, 2])
            .set_toml("data.train", &set("train"))
            .set_toml("data.val", &set("val"))
            .eval(&eval)
    };
    let file = exp("f195").write(&dir.join("ds.toml"));
    let f = common::s(&file);
    ok(calibconv_in(dir, &["train", f, "-q"]));
    let metrics = dir.join("runs/ds/eval/f195-standard/metrics.json");
    file_containing(&metrics, &["\"rmse\""]);
    // The F165 camera on F195 images: a clear error naming the folder.
    exp("f165").write(&file);
    let e = failed(calibconv_in(dir, &["eval", f, "-q"]));
    assert_contains(&e, &["sets/f195", "is not the experiment's"]);
}
