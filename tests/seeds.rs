//! Seeds as a sweep axis: replicates in `OUTPUT/seed-S/NAME`, fine-tunings paired within a
//! seed (same baseline, same batch order and augmentations whatever the kernel), a baseline
//! shared across seeds on request, `study.json`, and SLURM arrays with one task per run and
//! seed.

mod common;

use std::path::Path;

use tch::Tensor;

use calibconv::data::Batch;
use calibconv::experiment::layout::{ResultsDir, RunDir};
use calibconv::experiment::run::open_training_source;
use calibconv::experiment::sweep::{self, Seeds};
use calibconv::experiment::{DefaultOpener, InitSpec};
use common::{calibconv_in, synth_tiny_f195};

/// A 32-px F195 data set (10 panoramas, 2 views each) in `dir/sets/f195`.
fn synth(dir: &Path) {
    synth_tiny_f195(&dir.join("sets"), 32);
}

/// A baseline (`init` None) or a fine-tuning of `bl` with `kernel` on the F195 set, with
/// colour-jitter augmentation.
fn experiment(dir: &Path, name: &str, kernel: &str, init: Option<&str>) -> String {
    format!(
        r#"name = "{name}"
task = "depth"
device = "cpu"
data_root = "{sets}"
output = "runs"

[model]
preset = "tiny"
kernel = "{kernel}"
{init}

[input]
camera = "{root}/data/cameras/f195.toml"
width = 32
padding = [0, 4]

[data]
train = {{ dataset = "f195", split = "train" }}
val = {{ dataset = "f195", split = "val" }}

[train]
steps = 2
batch_size = 3
augment = {{ jitter = 0.3 }}

[optimizer]
lr = 1e-3

[[eval]]
name = "f195-{kernel}"
data = {{ dataset = "f195", split = "test" }}
"#,
        sets = dir.join("sets").display(),
        root = env!("CARGO_MANIFEST_DIR"),
        init = init
            .map(|i| format!("init = {{ experiment = \"{i}\" }}"))
            .unwrap_or_default()
    )
}

fn write_set(dir: &Path) {
    std::fs::create_dir_all(dir.join("exp")).unwrap();
    let e = dir.join("exp");
    std::fs::write(e.join("bl.toml"), experiment(dir, "bl", "standard", None)).unwrap();
    for k in ["standard", "calibrated"] {
        std::fs::write(
            e.join(format!("ft-{k}.toml")),
            experiment(dir, &format!("ft-{k}"), k, Some("bl")),
        )
        .unwrap();
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
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    synth(dir);
    write_set(dir);
    std::env::set_current_dir(dir).unwrap();
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
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    synth(dir);
    write_set(dir);
    let e = dir.join("exp");
    std::fs::create_dir_all(e.join("profiles")).unwrap();
    std::fs::write(
        e.join("profiles/rep.toml"),
        "seeds = [1, 2, 3]\n[slurm]\ncpus_per_task = 1\ntime = \"00:10:00\"\n",
    )
    .unwrap();
    let exp_dir = e.display().to_string();
    let o = calibconv_in(
        dir,
        &[
            "sweep",
            &exp_dir,
            "--profile",
            "rep",
            "--seeds",
            "0,1",
            "--jobs",
            "2",
            "-q",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    // Each run's line says where its time went.
    assert!(
        err.contains("seed-1/ft-calibrated: train:") && err.contains("steps "),
        "{err}"
    );
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
    assert_eq!(study.profile, "rep");
    assert_eq!(study.runs.len(), 6);

    let slurm = dir.join("slurm");
    let o = calibconv_in(
        dir,
        &[
            "sweep",
            &exp_dir,
            "--profile",
            "rep",
            "--emit-slurm",
            &slurm.display().to_string(),
            "--slurm-set",
            "mem=1G",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let l0 = std::fs::read_to_string(slurm.join("level-0.sbatch")).unwrap();
    let l1 = std::fs::read_to_string(slurm.join("level-1.sbatch")).unwrap();
    assert!(
        l0.contains("#SBATCH --array=0-2\n")
            && l0.contains("RUNS=(bl bl bl)\n")
            && l0.contains("SEEDS=(1 2 3)\n"),
        "{l0}"
    );
    assert!(
        l0.contains("#SBATCH --time=00:10:00\n#SBATCH --cpus-per-task=1\n#SBATCH --mem=1G\n"),
        "{l0}"
    );
    assert!(!l0.contains("gres"), "{l0}");
    assert!(l1.contains("#SBATCH --array=0-5\n"), "{l1}");
    assert!(
        l1.contains("--seeds 1,2,3 --only-seed \"${SEEDS[$SLURM_ARRAY_TASK_ID]}\""),
        "{l1}"
    );
}
