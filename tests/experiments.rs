//! Every file in `experiments/` parses and resolves, experiment names are unique (they name run
//! directories), and `init = { experiment = ... }` names an experiment that exists.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use calibconv::experiment::{self, InitSpec};

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
    std::env::set_current_dir(env!("CARGO_MANIFEST_DIR")).unwrap();
    let mut files = Vec::new();
    toml_files(Path::new("experiments"), &mut files);
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
    std::env::set_current_dir(env!("CARGO_MANIFEST_DIR")).unwrap();
    let dir = Path::new("experiments/paper");
    let mut profiles = Vec::new();
    toml_files(&dir.join("profiles"), &mut profiles);
    profiles.sort();
    let names: Vec<String> = profiles
        .iter()
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["paper", "quick"]);
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
    }
}
