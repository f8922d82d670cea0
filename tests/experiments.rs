//! Every file in `experiments/` parses and resolves, experiment names are unique (they name run
//! directories), and `init = { experiment = ... }` names an experiment that exists.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use calibconv::experiment::{self, InitSpec};

fn toml_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            toml_files(&path, out);
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
