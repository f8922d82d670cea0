//! Sweeps on tiny toy experiments: dependency order, skipping complete runs, a failed run that
//! does not stop the others (and blocks its dependants), overrides recorded in each run; the
//! SLURM scripts' structure; the report of the results.

mod common;

use std::path::Path;

use calibconv::experiment::layout::{RunDir, SweepStatus};
use calibconv::experiment::profile::Override;
use calibconv::experiment::sweep::{self, Outcome, State, SweepOptions};
use calibconv::experiment::DefaultOpener;
use common::{calibconv_in, synth_tiny_f195};

/// A tiny toy experiment: 2 steps of the tiny U-Net on 16x16 toy images.
fn toy(name: &str, init: Option<&str>, train: &str) -> String {
    format!(
        r#"name = "{name}"
task = "depth"
output = "runs"
device = "cpu"

[model]
preset = "tiny"
kernel = "standard"
{init}

[input]
camera = "{root}/data/cameras/f195.toml"
padding = [8, 0]
size = [16, 16]

[data]
train = {train}
val = {{ toy = 4, split = "val" }}

[train]
epochs = 5
batch_size = 2

[optimizer]
lr = 1e-3

[[eval]]
name = "f195-standard"
data = {{ toy = 4, split = "test" }}
"#,
        root = env!("CARGO_MANIFEST_DIR"),
        init = init
            .map(|i| format!("init = {{ experiment = \"{i}\" }}"))
            .unwrap_or_default()
    )
}

fn write_set(dir: &Path) {
    let ok = r#"{ toy = 4, split = "train" }"#;
    let missing = r#"{ dataset = "no-such-folder", split = "train" }"#;
    std::fs::write(dir.join("bl.toml"), toy("bl", None, ok)).unwrap();
    std::fs::write(dir.join("ft.toml"), toy("ft", Some("bl"), ok)).unwrap();
    std::fs::write(dir.join("broken.toml"), toy("broken", None, missing)).unwrap();
    std::fs::write(
        dir.join("after-broken.toml"),
        toy("after-broken", Some("broken"), ok),
    )
    .unwrap();
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
    // Output paths are relative to the current directory: run inside the temporary folder.
    std::env::set_current_dir(dir).unwrap();
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
    assert_eq!(rec.profile, "tiny");
    assert_eq!(rec.overrides, ["train.batch_size=1"]);
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

    // The report of these results: tables, REPORT.md with each run.
    let files =
        calibconv::report::results::write_report(&dir.join("runs"), &dir.join("report")).unwrap();
    assert!(files.iter().any(|f| f.ends_with("table_depth.md")));
    let table = std::fs::read_to_string(dir.join("report/table_depth.csv")).unwrap();
    assert!(
        table.starts_with("block,dataset,kernel,n,mre,mre_ci95_half_width,mae,"),
        "{table}"
    );
    assert!(table.contains("BL,F195,standard,1,"), "{table}");
    assert!(table.contains("FT,F195,standard,1,"), "{table}");
    let report = std::fs::read_to_string(dir.join("report/REPORT.md")).unwrap();
    assert!(report.contains("| FT | F195 | standard | 1 |") && report.contains("[ft](../runs/ft)"));
    assert!(dir.join("report/verdict.json").is_file());
}

#[test]
fn the_command_exits_non_zero_after_a_failure_and_writes_slurm_scripts_by_level() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_set(dir);
    let d = dir.display().to_string();
    let o = calibconv_in(
        dir,
        &["sweep", &d, "--profile", "tiny", "--only", "*broken", "-q"],
    );
    let text = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success());
    assert!(
        text.contains("FAILED broken") && text.contains("BLOCKED after-broken"),
        "{text}"
    );

    let slurm = dir.join("slurm");
    let o = calibconv_in(
        dir,
        &[
            "sweep",
            &d,
            "--profile",
            "tiny",
            "--set",
            "optimizer.lr=1e-4",
            "--emit-slurm",
            &slurm.display().to_string(),
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let l0 = std::fs::read_to_string(slurm.join("level-0.sbatch")).unwrap();
    let l1 = std::fs::read_to_string(slurm.join("level-1.sbatch")).unwrap();
    assert!(l0.starts_with("#!/bin/bash\n"));
    assert!(
        l0.contains("#SBATCH --array=0-1\n") && l0.contains("RUNS=(bl broken)\n"),
        "{l0}"
    );
    assert!(l1.contains("#SBATCH --array=0-1\n") && l1.contains("RUNS=(after-broken ft)\n"));
    assert!(
        l1.contains("--profile") && l1.contains("--set 'optimizer.lr=0.0001'"),
        "{l1}"
    );
    assert!(
        l1.contains("--only \"${RUNS[$SLURM_ARRAY_TASK_ID]}\""),
        "{l1}"
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
    let exp = |eval_camera: &str| {
        format!(
            r#"name = "ds"
task = "depth"
device = "cpu"
data_root = "{sets}"
output = "{out}"

[model]
preset = "tiny"
kernel = "standard"

[input]
camera = "{root}/data/cameras/f195.toml"
width = 16
padding = [0, 2]

[data]
train = {{ dataset = "f195", split = "train" }}
val = {{ dataset = "f195", split = "val" }}

[train]
steps = 2
batch_size = 2

[optimizer]
lr = 1e-3

[[eval]]
name = "f195-standard"
data = {{ dataset = "f195", split = "test" }}
camera = "{root}/data/cameras/{eval_camera}.toml"
"#,
            sets = dir.join("sets").display(),
            out = dir.join("runs").display(),
            root = env!("CARGO_MANIFEST_DIR"),
        )
    };
    let file = dir.join("ds.toml");
    std::fs::write(&file, exp("f195")).unwrap();
    let o = calibconv_in(dir, &["train", &file.display().to_string(), "-q"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m = std::fs::read_to_string(dir.join("runs/ds/eval/f195-standard/metrics.json")).unwrap();
    assert!(m.contains("\"rmse\""), "{m}");
    // The F165 camera on F195 images: a clear error naming the folder.
    std::fs::write(&file, exp("f165")).unwrap();
    let o = calibconv_in(dir, &["eval", &file.display().to_string(), "-q"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        e.contains("sets/f195") && e.contains("is not the experiment's"),
        "{e}"
    );
}
