//! Every file in `experiments/` parses and resolves, experiment names are unique (they name run
//! directories), and `init = { experiment = ... }` names an experiment that exists.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use calibconv::experiment::{self, InitSpec};

use crate::common::{self, calibconv_command};

/// The repository root, after checking that it is the current directory: the shipped
/// experiment files name cameras, data sets and outputs relative to the current directory, which
/// Cargo sets to the package root for its tests (and no test of this binary changes).
fn repo_root() -> &'static Path {
    let root = common::root();
    let cwd = std::env::current_dir().unwrap();
    assert_eq!(
        cwd.canonicalize().unwrap(),
        root.canonicalize().unwrap(),
        "the shipped experiment files resolve against the current directory: run from the root"
    );
    root
}

fn toml_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            // Profiles are overlays, tested below with their experiments.
            if path.file_name().is_some_and(|n| n != "profiles") {
                toml_files(&path, out);
            }
        } else if path.extension().is_some_and(|e| e == "toml") {
            out.push(path);
        }
    }
}

#[test]
fn every_experiment_file_parses_and_resolves() {
    // Relative paths in experiment files are relative to the repository root.
    let root = repo_root();
    let mut files = Vec::new();
    toml_files(&root.join("experiments"), &mut files);
    files.sort();
    assert!(files.len() >= 2, "no experiment files found");
    let mut by_name = BTreeMap::new();
    let mut inits = Vec::new();
    for f in &files {
        let exp = experiment::load(f).unwrap_or_else(|e| panic!("{e}"));
        if let Some(prev) = by_name.insert(exp.name.clone(), f.clone()) {
            panic!(
                "experiment name `{}` used by {} and {}",
                exp.name,
                prev.display(),
                f.display()
            );
        }
        if let Some(InitSpec::Experiment { name, .. }) = &exp.init {
            inits.push((f.clone(), name.clone()));
        }
    }
    for (f, name) in inits {
        assert!(
            by_name.contains_key(&name),
            "{}: init names experiment `{name}`, which no file in experiments/ defines",
            f.display()
        );
    }
    for task in ["depth", "segmentation"] {
        assert!(
            files.iter().any(|f| std::fs::read_to_string(f)
                .unwrap()
                .contains(&format!("task = \"{task}\""))),
            "no example for task {task}"
        );
    }
}

#[test]
fn every_profile_applies_to_its_experiments_and_the_paper_set_is_complete() {
    use calibconv::experiment::sweep;
    let dir = &repo_root().join("experiments/paper");
    let mut profiles = Vec::new();
    toml_files(&dir.join("profiles"), &mut profiles);
    profiles.sort();
    let names: Vec<String> = profiles
        .iter()
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["paper", "quick", "study"]);
    for name in &names {
        let profile = sweep::find_profile(dir, name).unwrap();
        let plan = sweep::plan(dir, &profile, &[], &[]).unwrap_or_else(|e| panic!("{name}: {e}"));
        // Table 1 and 2: one BL run per task with its six evaluations, five FT runs per task
        // starting from it.
        assert_eq!(plan.len(), 12, "{name}");
        for task in ["depth", "seg"] {
            let bl = plan
                .iter()
                .find(|p| p.exp.name == format!("paper-{task}-bl-pers"))
                .unwrap();
            assert_eq!(bl.level, 0);
            let evals: Vec<(&str, &str)> = bl
                .exp
                .evals
                .iter()
                .map(|e| (e.name.as_str(), e.kernel.as_str()))
                .collect();
            assert_eq!(
                evals,
                [
                    ("pers-standard", "standard"),
                    ("f195-standard", "standard"),
                    ("f195-calibrated", "calibrated"),
                    ("f165-standard", "standard"),
                    ("f165-calibrated", "calibrated"),
                    ("f165-rectified", "standard"),
                ]
            );
            let ft: Vec<&str> = plan
                .iter()
                .filter(|p| p.deps == [bl.exp.name.clone()])
                .map(|p| p.exp.name.as_str())
                .collect();
            assert_eq!(ft.len(), 5, "{name} {task}: {ft:?}");
            for p in plan.iter().filter(|p| p.deps == [bl.exp.name.clone()]) {
                assert_eq!(p.level, 1);
                // Calibrated kernels use the fisheye camera of the data set they see.
                let set = p.exp.name.rsplit('-').nth(1).unwrap();
                if p.exp.kernel.as_str() == "calibrated" {
                    assert!(p.exp.input.camera_file.ends_with(format!("{set}.toml")));
                }
                if p.exp.name.ends_with("rectified") {
                    assert!(p.exp.input.camera_file.ends_with("rect-f165.toml"));
                }
            }
        }
        if name == "quick" {
            let bl = &plan[0].exp;
            assert_eq!(bl.input.size, [64, 64]);
            assert_eq!(bl.model.base, 8);
        }
        // Every profile replicates over three seeds, each fine-tuning from its own seed's
        // baseline; SLURM resources: one GPU for paper, none for quick and study.
        assert_eq!(profile.seeds.as_deref(), Some(&[0, 1, 2][..]), "{name}");
        let seeds = sweep::Seeds::from_profile(&profile, None).unwrap();
        let replicated = sweep::plan_seeds(dir, &profile, &[], &[], &seeds).unwrap();
        assert_eq!(replicated.len(), 36, "{name}");
        for p in &replicated {
            let s = p.seed.unwrap();
            assert_eq!(p.exp.seed, s);
            assert!(p.exp.run_dir.ends_with(format!("seed-{s}/{}", p.exp.name)));
            if p.level == 1 {
                assert!(p.deps.len() == 1 && p.deps[0].starts_with(&format!("seed-{s}/")));
            }
        }
        let spec = calibconv::experiment::slurm::SlurmSpec::resolve(&profile, &[]).unwrap();
        if name == "paper" {
            assert_eq!(spec.gres.as_deref(), Some("gpu:1"));
        } else {
            // quick and study run on CPUs.
            assert_eq!((spec.gres.as_deref(), spec.cpus_per_task), (None, Some(1)));
        }
        if name == "study" {
            // 160 px wide, the small U-Net at depth 3 (see the profile's header).
            let bl = &plan[0].exp;
            assert_eq!(
                (bl.input.size, bl.model.base, bl.model.depth),
                ([144, 160], 16, 3)
            );
        }
    }
}

/// The quick data sets (`make demo`): at least 160 test images per set, from panoramas none
/// of whose views are in the training or validation split.
#[test]
fn quick_data_sets_test_on_160_images_of_panoramas_not_used_in_training() {
    use std::collections::BTreeSet;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    // The configuration as `make demo` runs it, on 16-px-high panoramas (the splits do not
    // depend on the panorama size) and one set.
    let o = calibconv_command(&[
        "synth",
        "--config",
        "data/synth-quick.toml",
        "--set",
        "f195",
    ])
    .args(["--pano-height", "16", "--out"])
    .arg(out.path())
    .current_dir(root)
    .output()
    .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let manifest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.path().join("f195/manifest.json")).unwrap(),
    )
    .unwrap();
    let split = |name: &str| -> Vec<String> {
        manifest["splits"][name]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap().to_string())
            .collect()
    };
    // Sample ids are PANORAMA_vVIEW.
    let panoramas = |ids: &[String]| -> BTreeSet<String> {
        ids.iter()
            .map(|i| i.rsplit_once("_v").unwrap().0.to_string())
            .collect()
    };
    let (train, val, test) = (split("train"), split("val"), split("test"));
    assert!(test.len() >= 160, "{} test images", test.len());
    let test_p = panoramas(&test);
    assert!(test_p.len() >= 20, "{} test panoramas", test_p.len());
    assert!(panoramas(&train).is_disjoint(&test_p));
    assert!(panoramas(&val).is_disjoint(&test_p));
    assert!(panoramas(&train).is_disjoint(&panoramas(&val)));
}

/// The field-of-view series plans with the study profile: standard and calibrated per lens of
/// data/cameras/kb*.toml, each starting from the study's Pers depth baseline.
#[test]
fn the_fov_series_pairs_every_lens_with_both_kernels() {
    use calibconv::experiment::sweep;
    let root = repo_root();
    let fov_dir = root.join("experiments/fov");
    let study = root.join("experiments/paper/profiles/study.toml");
    let profile = sweep::find_profile(&fov_dir, common::s(&study)).unwrap();
    let plan = sweep::plan(&fov_dir, &profile, &[], &[]).unwrap();
    for fov in [120, 150, 180, 210, 240] {
        for kernel in ["standard", "calibrated"] {
            let name = format!("fov-depth-ft-kb{fov}-{kernel}");
            let p = plan
                .iter()
                .find(|p| p.exp.name == name)
                .unwrap_or_else(|| panic!("no {name}"));
            assert!(
                matches!(&p.exp.init, Some(InitSpec::Experiment { name, .. }) if name == "paper-depth-bl-pers"),
                "{name}: not from the study's depth baseline"
            );
            assert!(root.join(format!("data/cameras/kb{fov}.toml")).is_file());
        }
    }
    assert_eq!(plan.len(), 10);
}

/// The open questions plan with the study profile from the study's Pers depth baseline: the
/// data-efficiency series pairs both kernels at 1/16, 1/8, 1/4 and 1/2 of F195's training views
/// with the same steps as the full fine-tuning, and the methods are the two kinds beyond the
/// paper's.
#[test]
fn the_open_questions_plan_from_the_depth_baseline() {
    use calibconv::experiment::{sweep, KernelName, SourceSpec};
    let root = repo_root();
    let study = root.join("experiments/paper/profiles/study.toml");
    let plan_of = |dir: &str| {
        let dir = root.join(dir);
        let profile = sweep::find_profile(&dir, common::s(&study)).unwrap();
        sweep::plan(&dir, &profile, &[], &[]).unwrap()
    };
    let from_baseline = |p: &sweep::Planned| matches!(&p.exp.init, Some(InitSpec::Experiment { name, .. }) if name == "paper-depth-bl-pers");
    let full = plan_of("experiments/paper");
    let full_ft = full
        .iter()
        .find(|p| p.exp.name == "paper-depth-ft-f195-calibrated")
        .unwrap();
    let efficiency = plan_of("experiments/data-efficiency");
    assert_eq!(efficiency.len(), 8);
    for (n, fraction) in [(16, 0.0625), (8, 0.125), (4, 0.25), (2, 0.5)] {
        for kernel in ["standard", "calibrated"] {
            let name = format!("eff-depth-ft-f195-1of{n}-{kernel}");
            let p = efficiency.iter().find(|p| p.exp.name == name).unwrap();
            assert!(from_baseline(p), "{name}");
            assert_eq!(p.exp.kernel.as_str(), kernel, "{name}");
            assert!(
                matches!(&p.exp.train_data, SourceSpec::Dataset { fraction: Some(f), .. } if *f == fraction),
                "{name}: {:?}",
                p.exp.train_data
            );
            assert_eq!(
                format!("{:?}", p.exp.train.length),
                format!("{:?}", full_ft.exp.train.length),
                "{name}: another training length than the full fine-tuning"
            );
        }
    }
    let methods = plan_of("experiments/methods");
    let kernels: Vec<KernelName> = methods.iter().map(|p| p.exp.kernel).collect();
    assert_eq!(kernels.len(), 2);
    for k in [KernelName::CamConv, KernelName::CalibratedLearned] {
        assert!(kernels.contains(&k), "{kernels:?}");
    }
    assert!(methods.iter().all(from_baseline));
}
