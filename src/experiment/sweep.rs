//! Sweeps: every experiment file of a folder, with a profile and overrides, run in dependency
//! order (a fine-tuning waits for the experiment named by its `model.init`).
//!
//! For each run the sweep looks at its run directory first:
//! - complete (`summary.json` and every evaluation's `metrics.json`): skipped;
//! - trained, some evaluations missing: evaluated;
//! - interrupted (`checkpoints/last.safetensors` without `summary.json`): resumed;
//! - otherwise: trained from the start.
//!
//! A run directory that holds another configuration (its `experiment.toml` differs from the
//! merged text as TOML) is a failure of that run, never overwritten. A failed run does not stop
//! the sweep; runs that depend on it are reported as blocked. Each run directory gets
//! `sweep.json`: the profile, the overrides, the merged experiment text, the git revision, the
//! action taken, its wall time and outcome (`config.json` and `run.json` hold the resolved
//! experiment and each invocation's git revision, as for `calibconv train`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use super::layout::{write_record, RunLock, SweepRecord, SweepStatus};
use super::profile::{self, Override, Profile};
use super::run::{self, git_revision, RunOptions};
use super::{Experiment, InitSpec, SourceOpener};
use crate::error::{Error, Result};
use crate::io::write_bytes_atomic;

/// One run of a sweep.
#[derive(Clone, Debug)]
pub struct Planned {
    pub exp: Experiment,
    /// The experiment file.
    pub file: PathBuf,
    /// The merged text it runs with.
    pub text: String,
    /// Names of the runs of this sweep it starts from.
    pub deps: Vec<String>,
    /// 0 for runs without dependencies in the sweep, else 1 + the deepest dependency's level.
    pub level: usize,
}

/// What a run directory holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum State {
    /// Nothing yet.
    New,
    /// Interrupted training.
    Interrupted,
    /// Trained; some evaluations missing.
    Trained,
    /// Trained and evaluated.
    Complete,
}

/// How a run ended in a sweep.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Already complete.
    Skipped,
    /// Ran (`action`: train, resume, evaluate) in `seconds`.
    Done { action: &'static str, seconds: f64 },
    /// Failed with this error (cause chain).
    Failed(String),
    /// Not run: a dependency failed or is blocked.
    Blocked(String),
}

impl Outcome {
    /// Whether the run failed or could not run.
    pub fn is_failure(&self) -> bool {
        matches!(self, Outcome::Failed(_) | Outcome::Blocked(_))
    }
}

/// Whether `name` matches `--only` `pattern`: a glob over the whole name (`*` any characters);
/// a pattern without `*` matches names that contain it.
pub fn matches(pattern: &str, name: &str) -> bool {
    fn glob(p: &[u8], s: &[u8]) -> bool {
        match p.split_first() {
            None => s.is_empty(),
            Some((b'*', rest)) => (0..=s.len()).any(|i| glob(rest, &s[i..])),
            Some((c, rest)) => s.first() == Some(c) && glob(rest, &s[1..]),
        }
    }
    if pattern.contains('*') {
        glob(pattern.as_bytes(), name.as_bytes())
    } else {
        name.contains(pattern)
    }
}

/// The experiment files of `dir` (`*.toml`, not its subfolders), sorted.
pub fn experiment_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "toml"))
        .collect();
    files.sort();
    Ok(files)
}

/// The profile named `name` of sweep folder `dir`: `DIR/profiles/NAME.toml`, or a file path.
pub fn find_profile(dir: &Path, name: &str) -> Result<Profile> {
    let as_file = PathBuf::from(name);
    let file = if as_file.is_file() {
        as_file
    } else {
        dir.join("profiles").join(format!("{name}.toml"))
    };
    if !file.is_file() {
        let known: Vec<String> = experiment_files(&dir.join("profiles"))
            .unwrap_or_default()
            .iter()
            .filter_map(|p| p.file_stem().map(|s| s.to_string_lossy().into_owned()))
            .collect();
        return Err(Error::InvalidArgument(format!(
            "no profile `{name}`: {} does not exist (profiles of {}: {})",
            file.display(),
            dir.display(),
            if known.is_empty() {
                "none".into()
            } else {
                known.join(", ")
            }
        )));
    }
    Profile::load(&file)
}

/// Reads, merges and resolves every experiment of `dir`, keeps those matching one of `only`
/// (all if empty), and orders them by dependency level, then name.
pub fn plan(
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    only: &[String],
) -> Result<Vec<Planned>> {
    let mut all = Vec::new();
    for file in experiment_files(dir)? {
        let text = std::fs::read_to_string(&file).map_err(|e| Error::io(&file, e))?;
        let merged = profile::apply(&file, &text, profile, overrides)?;
        let exp = super::parse(&merged, &file)?.resolve(&file, &merged)?;
        all.push((file, merged, exp));
    }
    let mut seen = BTreeSet::new();
    for (file, _, exp) in &all {
        if !seen.insert(exp.name.clone()) {
            return Err(Error::Config {
                path: file.clone(),
                field: "name".into(),
                message: format!("`{}` names two experiments of {}", exp.name, dir.display()),
            });
        }
    }
    let selected: Vec<_> = all
        .into_iter()
        .filter(|(_, _, e)| {
            only.is_empty()
                || only.iter().any(|p| {
                    // An exact name selects that run only.
                    if seen.contains(p) {
                        &e.name == p
                    } else {
                        matches(p, &e.name)
                    }
                })
        })
        .collect();
    if selected.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "no experiment of {} matches {}",
            dir.display(),
            only.join(", ")
        )));
    }
    let names: BTreeSet<String> = selected.iter().map(|(_, _, e)| e.name.clone()).collect();
    let deps: BTreeMap<String, Vec<String>> = selected
        .iter()
        .map(|(_, _, e)| {
            let d = match &e.init {
                Some(InitSpec::Experiment { name, .. }) if names.contains(name) => {
                    vec![name.clone()]
                }
                _ => vec![],
            };
            (e.name.clone(), d)
        })
        .collect();
    // Levels by repeated relaxation; more rounds than runs means a cycle.
    let mut level: BTreeMap<String, usize> = names.iter().map(|n| (n.clone(), 0)).collect();
    for round in 0..=names.len() {
        let mut changed = false;
        for (n, ds) in &deps {
            let l = ds.iter().map(|d| level[d] + 1).max().unwrap_or(0);
            if l != level[n] {
                level.insert(n.clone(), l);
                changed = true;
            }
        }
        if !changed {
            break;
        }
        if round == names.len() {
            return Err(Error::InvalidArgument(format!(
                "the experiments of {} start from each other in a cycle",
                dir.display()
            )));
        }
    }
    let mut out: Vec<Planned> = selected
        .into_iter()
        .map(|(file, text, exp)| Planned {
            deps: deps[&exp.name].clone(),
            level: level[&exp.name],
            exp,
            file,
            text,
        })
        .collect();
    out.sort_by(|a, b| (a.level, &a.exp.name).cmp(&(b.level, &b.exp.name)));
    Ok(out)
}

/// What the run directory of `exp` holds. A `summary.json` that does not read as a
/// [`super::layout::Summary`] is an error naming it.
pub fn state(exp: &Experiment) -> Result<State> {
    let dir = run::run_dir(exp);
    Ok(if dir.summary_if_any()?.is_some() {
        let evaluated = exp
            .evals
            .iter()
            .all(|e| dir.metrics_json(&e.name).is_file());
        if evaluated {
            State::Complete
        } else {
            State::Trained
        }
    } else if dir.last_checkpoint().is_file() {
        State::Interrupted
    } else {
        State::New
    })
}

/// `Err` if the run directory holds another configuration than `text`.
fn check_same_config(exp: &Experiment, text: &str) -> Result<()> {
    let stored = run::run_dir(exp).experiment_toml();
    let old = match std::fs::read_to_string(&stored) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(&stored, e)),
    };
    let parse = |t: &str| toml::from_str::<toml::Table>(t).ok();
    if parse(&old) != parse(text) {
        return Err(Error::Config {
            path: exp.file.clone(),
            field: "name".into(),
            message: format!(
                "{} holds a run of another configuration (see its experiment.toml): remove \
                 it, or name another `output` (profile or --set output=...)",
                exp.run_dir.display()
            ),
        });
    }
    Ok(())
}

/// How a sweep runs.
pub struct SweepOptions<'a> {
    pub profile: &'a Profile,
    pub overrides: &'a [Override],
    /// Runs at a time within a dependency level (at least 1).
    pub jobs: usize,
    /// An overall progress bar on stderr.
    pub progress: bool,
    pub opener: &'a (dyn SourceOpener + Sync),
}

/// Runs `p` holding its lock (taken first: a run another process holds fails at once and its
/// records are left alone).
fn run_one(p: &Planned, opts: &SweepOptions<'_>) -> Outcome {
    let lock = match run::run_dir(&p.exp).lock() {
        Ok(l) => l,
        Err(e) => return Outcome::Failed(cause_chain(&e)),
    };
    let outcome = run_locked(p, opts, &lock).unwrap_or_else(|e| Outcome::Failed(cause_chain(&e)));
    record(p, opts, &outcome, &lock)
        .map(|()| outcome.clone())
        .unwrap_or_else(|e| {
            Outcome::Failed(format!("cannot write sweep.json: {}", cause_chain(&e)))
        })
}

/// An error and its causes, `: `-separated.
fn cause_chain(e: &Error) -> String {
    let mut msg = e.to_string();
    let mut src = std::error::Error::source(e);
    while let Some(c) = src {
        msg += &format!(": {c}");
        src = c.source();
    }
    msg
}

fn run_locked(p: &Planned, opts: &SweepOptions<'_>, lock: &RunLock) -> Result<Outcome> {
    let exp = &p.exp;
    check_same_config(exp, &p.text)?;
    let before = state(exp)?;
    if before == State::Complete {
        return Ok(Outcome::Skipped);
    }
    let ropts = RunOptions {
        resume: before == State::Interrupted,
        progress: false,
        verbose: false,
        opener: opts.opener,
    };
    let start = Instant::now();
    let action = match before {
        State::Trained => {
            let t = Instant::now();
            run::evaluate_locked(exp, None, &[], &ropts, lock)?;
            run::record_evaluation_time(exp, t.elapsed().as_secs_f64())?;
            "evaluate"
        }
        State::Interrupted => {
            run::train_locked(exp, &ropts, lock)?;
            "resume"
        }
        _ => {
            run::train_locked(exp, &ropts, lock)?;
            "train"
        }
    };
    Ok(Outcome::Done {
        action,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Writes the run's `sweep.json` (under its lock; nothing for a skipped run).
fn record(p: &Planned, opts: &SweepOptions<'_>, outcome: &Outcome, _lock: &RunLock) -> Result<()> {
    let (status, action, seconds, error) = match outcome {
        Outcome::Skipped => return Ok(()),
        Outcome::Done { action, seconds } => (
            SweepStatus::Done,
            Some(action.to_string()),
            Some(*seconds),
            None,
        ),
        Outcome::Failed(e) => (SweepStatus::Failed, None, None, Some(e.clone())),
        Outcome::Blocked(e) => (SweepStatus::Blocked, None, None, Some(e.clone())),
    };
    let doc = SweepRecord {
        experiment: p.exp.name.clone(),
        file: p.file.clone(),
        profile: opts.profile.name.clone(),
        profile_file: opts.profile.file.clone(),
        overrides: opts
            .overrides
            .iter()
            .map(|o| format!("{}={}", o.key, o.value))
            .collect(),
        seed: None,
        level: p.level,
        depends_on: p.deps.clone(),
        git: git_revision(),
        status,
        action,
        seconds,
        error,
        experiment_text: p.text.clone(),
    };
    write_record(&run::run_dir(&p.exp).sweep_json(), &doc)
}

/// A blocked run: recorded in its `sweep.json` if its folder exists and is not in use.
fn record_blocked(p: &Planned, opts: &SweepOptions<'_>, why: String) -> Outcome {
    let outcome = Outcome::Blocked(why);
    if p.exp.run_dir.is_dir() {
        if let Ok(lock) = run::run_dir(&p.exp).lock() {
            let _ = record(p, opts, &outcome, &lock);
        }
    }
    outcome
}

/// A line above the progress bar, or on stderr when there is none.
fn say(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

/// Runs `plan` level by level, `opts.jobs` runs at a time; returns each run's outcome in plan
/// order. Failures are outcomes, not errors.
pub fn run_sweep(plan: &[Planned], opts: &SweepOptions<'_>) -> Vec<(String, Outcome)> {
    let bar = if opts.progress {
        let b = indicatif::ProgressBar::new(plan.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {pos}/{len} runs {msg}",
            )
            .expect("template")
            .progress_chars("=> "),
        );
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let outcomes: Mutex<BTreeMap<String, Outcome>> = Mutex::new(BTreeMap::new());
    let max_level = plan.iter().map(|p| p.level).max().unwrap_or(0);
    for level in 0..=max_level {
        let queue: Mutex<Vec<&Planned>> =
            Mutex::new(plan.iter().filter(|p| p.level == level).rev().collect());
        let workers = opts.jobs.max(1);
        std::thread::scope(|s| {
            for _ in 0..workers {
                s.spawn(|| loop {
                    let Some(p) = queue.lock().expect("queue").pop() else {
                        break;
                    };
                    let blocked = {
                        let done = outcomes.lock().expect("outcomes");
                        p.deps
                            .iter()
                            .find(|d| done.get(*d).is_some_and(Outcome::is_failure))
                            .map(|d| format!("its initial weights come from `{d}`, which failed"))
                    };
                    bar.set_message(p.exp.name.clone());
                    let outcome = match blocked {
                        Some(b) => record_blocked(p, opts, b),
                        None => run_one(p, opts),
                    };
                    let line = match &outcome {
                        Outcome::Skipped => "complete, skipped".to_string(),
                        Outcome::Done { action, seconds } => format!("{action}: {seconds:.1} s"),
                        Outcome::Failed(e) => format!("FAILED: {e}"),
                        Outcome::Blocked(e) => format!("blocked: {e}"),
                    };
                    say(&bar, format!("{}: {line}", p.exp.name));
                    bar.inc(1);
                    outcomes
                        .lock()
                        .expect("outcomes")
                        .insert(p.exp.name.clone(), outcome);
                });
            }
        });
    }
    bar.finish_and_clear();
    let mut done = outcomes.into_inner().expect("outcomes");
    plan.iter()
        .map(|p| {
            let o = done.remove(&p.exp.name).expect("every run has an outcome");
            (p.exp.name.clone(), o)
        })
        .collect()
}

/// Writes SLURM batch scripts for `plan` into `out`: `level-K.sbatch` (one job array per
/// dependency level; task `i` runs `calibconv sweep DIR --only NAME_i` with the same profile
/// and overrides, so skipping and resuming work as on one machine) and `submit.sh`, which
/// submits them in order, each level `--dependency=afterok` on the one before. Returns the
/// files written.
pub fn emit_slurm(
    plan: &[Planned],
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    out: &Path,
) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let quote = |s: &str| format!("'{}'", s.replace('\'', "'\\''"));
    // The binary that wrote the scripts (the cluster shares the file system), else `calibconv`
    // from PATH.
    let exe = std::env::current_exe()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|_| "calibconv".into());
    let mut common = format!(
        "{} sweep {}",
        quote(&exe),
        quote(&dir.display().to_string())
    );
    if let Some(f) = &profile.file {
        common += &format!(" --profile {}", quote(&f.display().to_string()));
    }
    for o in overrides {
        common += &format!(" --set {}", quote(&format!("{}={}", o.key, o.value)));
    }
    let max_level = plan.iter().map(|p| p.level).max().unwrap_or(0);
    let mut files = Vec::new();
    let mut submit = String::from(
        "#!/bin/bash\n# Submits the sweep's job arrays, each level after the one before succeeded.\n\
         set -euo pipefail\ncd \"$(dirname \"$0\")\"\n",
    );
    for level in 0..=max_level {
        let names: Vec<&str> = plan
            .iter()
            .filter(|p| p.level == level)
            .map(|p| p.exp.name.as_str())
            .collect();
        let file = out.join(format!("level-{level}.sbatch"));
        let text = format!(
            "#!/bin/bash\n\
             #SBATCH --job-name=calibconv-level-{level}\n\
             #SBATCH --array=0-{last}\n\
             #SBATCH --gres=gpu:1\n\
             #SBATCH --cpus-per-task=8\n\
             #SBATCH --time=24:00:00\n\
             #SBATCH --output=slurm-%A_%a.out\n\
             # Dependency level {level}: {n} run(s); submit with submit.sh (afterok on level {prev}).\n\
             set -euo pipefail\n\
             cd {root}\n\
             RUNS=({runs})\n\
             srun {common} --only \"${{RUNS[$SLURM_ARRAY_TASK_ID]}}\"\n",
            last = names.len() - 1,
            n = names.len(),
            prev = level.saturating_sub(1),
            root = quote(
                &std::env::current_dir()
                    .map_err(|e| Error::io(Path::new("."), e))?
                    .display()
                    .to_string()
            ),
            runs = names.join(" "),
        );
        write_bytes_atomic(&file, text.as_bytes())?;
        if level == 0 {
            submit += &format!("j0=$(sbatch --parsable level-{level}.sbatch)\n");
        } else {
            submit += &format!(
                "j{level}=$(sbatch --parsable --dependency=afterok:$j{prev} level-{level}.sbatch)\n",
                prev = level - 1
            );
        }
        files.push(file);
    }
    submit += "echo \"submitted:";
    for level in 0..=max_level {
        submit += &format!(" $j{level}");
    }
    submit += "\"\n";
    let sub = out.join("submit.sh");
    write_bytes_atomic(&sub, submit.as_bytes())?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        for f in files.iter().chain(std::iter::once(&sub)) {
            let _ = std::fs::set_permissions(f, std::fs::Permissions::from_mode(0o755));
        }
    }
    files.push(sub);
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_patterns_are_globs_or_substrings() {
        assert!(matches("depth", "paper-depth-bl-pers"));
        assert!(matches("*-ft-*", "paper-seg-ft-f195-standard"));
        assert!(!matches("*-ft", "paper-seg-ft-f195-standard"));
        assert!(matches("paper-*-bl-*", "paper-seg-bl-pers"));
        assert!(!matches("seg", "paper-depth-bl-pers"));
    }
}
