//! Seeds as a sweep axis: replicates in `OUTPUT/seed-S/NAME`, fine-tunings paired within a
//! seed (same baseline, same batch order and augmentations whatever the kernel), a baseline
//! shared across seeds on request, `study.json`, and SLURM arrays with one task per run and
//! seed.

use std::path::Path;

use tch::Tensor;

use calibconv::data::Batch;
use calibconv::experiment::layout::{ResultsDir, RunDir};
use calibconv::experiment::run::open_training_source;
use calibconv::experiment::sweep::{self, Seeds};
use calibconv::experiment::{DefaultOpener, InitSpec};

use crate::common::experiment::ExperimentFile;
use crate::common::{self, assert_contains, calibconv_in, file_containing, ok, synth_tiny_f195};

/// A baseline (`init` None) or a fine-tuning of `bl` with `kernel` on the F195 set, with
/// colour-jitter augmentation.
fn experiment(dir: &Path, name: &str, kernel: &str, init: Option<&str>) -> ExperimentFile {
    let set = |split: &str| format!(r#"{{ dataset = "f195", split = "{split}" }}"#);
    let e = ExperimentFile::tiny(name)
        .set_path("data_root", &dir.join("sets"))
        .set_path("output", &dir.join("runs"))
        .set("model.kernel", kernel)
        .remove("input.size")
        .set("input.width", 32)
        .set("input.padding", vec![0, 4])
        .set_toml("data.train", &set("train"))
        .set_toml("data.val", &set("val"))
        .set("train.batch_size", 3)
        .set_toml("train.augment", "{ jitter = 0.3 }")
        .eval(&format!(
            r#"{{ name = "f195-{kernel}", data = {} }}"#,
            set("test")
        ));
    match init {
        Some(i) => e.set_toml("model.init", &format!(r#"{{ experiment = "{i}" }}"#)),
        None => e,
    }
}

/// A temporary folder with a 32-px F195 data set (10 panoramas, 2 views each) in
/// `sets/f195` and, in `exp/`, a baseline `bl` and its fine-tunings `ft-standard` and
/// `ft-calibrated`.
fn study() -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    synth_tiny_f195(&tmp.path().join("sets"), 32);
    write_set(tmp.path());
    tmp
}

fn write_set(dir: &Path) {
    let e = dir.join("exp");
    std::fs::create_dir_all(&e).unwrap();
    experiment(dir, "bl", "standard", None).write(&e.join("bl.toml"));
    for k in ["standard", "calibrated"] {
        let name = format!("ft-{k}");
        experiment(dir, &name, k, Some("bl")).write(&e.join(format!("{name}.toml")));
    }
}

/// Every batch of the first two epochs: sample ids and images (augmented).
fn batches(exp: &calibconv::experiment::Experiment) -> Vec<(Vec<String>, Tensor)> {
    let src = open_training_source(exp, &DefaultOpener).unwrap();
    let mut out = Vec::new();
    for epoch in 0..2 {
        for b in src.batches(epoch, 0) {
            let Batch { ids, image, .. } = b.unwrap();
            out.push((ids, image));
        }
    }
    out
}

#[test]
fn seeds_replicate_the_sweep_and_fine_tunings_of_one_seed_see_the_same_batches() {
    let tmp = study();
    let dir = tmp.path();
    let profile = Default::default();
    let seeds = Seeds {
        seeds: vec![4, 7],
        ..Default::default()
    };
    let plan = sweep::plan_seeds(&dir.join("exp"), &profile, &[], &[], &seeds).unwrap();
    let keys: Vec<(String, usize)> = plan.iter().map(|p| (p.key(), p.level)).collect();
    let want: Vec<(String, usize)> = [
        ("seed-4/bl", 0),
        ("seed-7/bl", 0),
        ("seed-4/ft-calibrated", 1),
        ("seed-4/ft-standard", 1),
        ("seed-7/ft-calibrated", 1),
        ("seed-7/ft-standard", 1),
    ]
    .iter()
    .map(|(k, l)| (k.to_string(), *l))
    .collect();
    assert_eq!(keys, want);
    let results = ResultsDir::new(dir.join("runs"));
    for p in &plan {
        let s = p.seed.unwrap();
        assert_eq!(p.exp.seed, s);
        assert_eq!(
            RunDir::new(&p.exp.run_dir),
            results.run_dir(Some(s), &p.exp.name)
        );
        if p.exp.name != "bl" {
            assert_eq!(p.deps, [format!("seed-{s}/bl")]);
            match &p.exp.init {
                Some(InitSpec::Experiment { checkpoints, .. }) => {
                    assert_eq!(*checkpoints, results.run_dir(Some(s), "bl").checkpoints())
                }
                i => panic!("{i:?}"),
            }
        }
    }

    // Paired: within a seed the kernel changes nothing in the data order or augmentation.
    let find = |key: &str| &plan.iter().find(|p| p.key() == key).unwrap().exp;
    let a = batches(find("seed-4/ft-standard"));
    let b = batches(find("seed-4/ft-calibrated"));
    let c = batches(find("seed-7/ft-standard"));
    assert_eq!(a.len(), b.len());
    assert!(a.len() >= 4, "{} batches", a.len());
    for ((ia, xa), (ib, xb)) in a.iter().zip(&b) {
        assert_eq!(ia, ib);
        assert!(xa.equal(xb), "the same batch, augmented differently");
    }
    // ... and the seed does (the test can fail).
    let ids = |v: &[(Vec<String>, Tensor)]| v.iter().map(|x| x.0.clone()).collect::<Vec<_>>();
    assert_ne!(ids(&a), ids(&c));

    // A shared baseline: planned once, in the first seed's folder; every seed starts from it.
    let shared = Seeds {
        share_baseline: true,
        ..seeds.clone()
    };
    let plan = sweep::plan_seeds(&dir.join("exp"), &profile, &[], &[], &shared).unwrap();
    let keys: Vec<String> = plan.iter().map(|p| p.key()).collect();
    assert_eq!(
        keys,
        [
            "seed-4/bl",
            "seed-4/ft-calibrated",
            "seed-4/ft-standard",
            "seed-7/ft-calibrated",
            "seed-7/ft-standard"
        ]
    );
    let ft7 = plan
        .iter()
        .find(|p| p.key() == "seed-7/ft-standard")
        .unwrap();
    assert_eq!(ft7.deps, ["seed-4/bl"]);
    assert_eq!(ft7.exp.seed, 7);
    match &ft7.exp.init {
        Some(InitSpec::Experiment { checkpoints, .. }) => {
            assert_eq!(*checkpoints, results.run_dir(Some(4), "bl").checkpoints())
        }
        i => panic!("{i:?}"),
    }
    // One seed of it (a SLURM task): the baseline is not planned, the fine-tuning still
    // starts from the first seed's.
    let one = Seeds {
        only: vec![7],
        ..shared.clone()
    };
    let plan = sweep::plan_seeds(
        &dir.join("exp"),
        &profile,
        &[],
        &["ft-standard".into()],
        &one,
    )
    .unwrap();
    assert_eq!(plan.len(), 1);
    assert!(plan[0].deps.is_empty());
    assert_eq!(plan[0].exp.init, ft7.exp.init);
    let bad = Seeds {
        only: vec![5],
        ..shared
    };
    assert!(sweep::plan_seeds(&dir.join("exp"), &profile, &[], &[], &bad).is_err());
}

#[test]
fn the_command_runs_every_seed_records_the_study_and_emits_slurm_arrays_by_seed() {
    let tmp = study();
    let dir = tmp.path();
    let e = dir.join("exp");
    std::fs::create_dir_all(e.join("profiles")).unwrap();
    std::fs::write(
        e.join("profiles/rep.toml"),
        "seeds = [1, 2, 3]\n[slurm]\ncpus_per_task = 1\ntime = \"00:10:00\"\n",
    )
    .unwrap();
    let exp_dir = e.display().to_string();
    let sweep = |extra: &[&str]| {
        let args = ["sweep", exp_dir.as_str(), "--profile", "rep"];
        ok(calibconv_in(dir, &[&args[..], extra].concat()))
    };
    let err = common::stderr(&sweep(&["--seeds", "0,1", "--jobs", "2", "-q"]));
    // Each run's line says where its time went.
    assert_contains(&err, &["seed-1/ft-calibrated: train:", "steps "]);
    let results = ResultsDir::new(dir.join("runs"));
    let reps = results.replicates().unwrap();
    assert_eq!(
        reps.iter().map(|r| r.seed).collect::<Vec<_>>(),
        [Some(0), Some(1)]
    );
    for r in &reps {
        let runs = ResultsDir::runs(r).unwrap();
        assert_eq!(runs.len(), 3);
        for run in runs {
            let s = run.read_summary().unwrap();
            assert_eq!(s.seed, r.seed);
            assert!(s.timing.evaluation.is_some());
            assert_eq!(run.read_sweep().unwrap().seed, r.seed);
        }
    }
    let study = results.study_if_any().unwrap().unwrap();
    assert_eq!(study.seeds, [0, 1]);
    assert_eq!(study.overlay.profile, "rep");
    assert_eq!(study.runs.len(), 6);

    let slurm = dir.join("slurm");
    sweep(&["--emit-slurm", common::s(&slurm), "--slurm-set", "mem=1G"]);
    let l0 = file_containing(
        &slurm.join("level-0.sbatch"),
        &[
            "#SBATCH --array=0-2\n",
            "RUNS=(bl bl bl)\n",
            "SEEDS=(1 2 3)\n",
            "#SBATCH --time=00:10:00\n#SBATCH --cpus-per-task=1\n#SBATCH --mem=1G\n",
        ],
    );
    assert!(!l0.contains("gres"), "{l0}");
    file_containing(
        &slurm.join("level-1.sbatch"),
        &[
            "#SBATCH --array=0-5\n",
            "--seeds 1,2,3 --only-seed \"${SEEDS[$SLURM_ARRAY_TASK_ID]}\"",
        ],
    );
}
