//! Sweeps: every experiment file of a folder, with a profile and overrides, run in dependency
//! order (a fine-tuning waits for the experiment named by its `model.init`).
//!
//! For each run the sweep looks at its run directory first:
//! - complete (`summary.json` and every evaluation's `metrics.json`): skipped;
//! - trained, some evaluations missing: evaluated;
//! - interrupted (`checkpoints/last.safetensors` without `summary.json`): resumed;
//! - otherwise: trained from the start.
//!
//! # Seeds: replicates of a sweep, paired within a seed
//!
//! With seeds (`--seeds 0,1,2`, or the profile's `seeds = [0, 1, 2]`; the flag wins) every
//! experiment runs once per seed `S`, with `seed = S` and its run directory in
//! `OUTPUT/seed-S/NAME/` (`OUTPUT` is the experiment's `output` after the profile). Without
//! seeds the run directories are `OUTPUT/NAME/`: one replicate with the experiments' own
//! seeds. The design is paired: within a seed, every fine-tuning starts from that seed's
//! baseline (`init = { experiment = ... }` resolves inside `OUTPUT/seed-S/`) and sees its
//! data in the order, and with the augmentations, of seed `S` (the training source is
//! shuffled by the experiment's seed; the kernel kind never enters the data order), so the
//! standard, calibrated and rectified fine-tunings of one calibration differ only in the
//! kernel. With `share_baseline = true` in the profile the baselines run once, in the first
//! seed's folder, and the fine-tunings of every seed start from them. `OUTPUT/study.json`
//! records the plan: profile, seeds, runs ([`super::layout::StudyRecord`]).
//!
//! When [`SweepOptions::stop`] is set (a signal: see [`crate::train::stop`]), the runs in
//! progress write their checkpoints and stop, no other run starts, and their outcome is
//! [`Outcome::Interrupted`]: the next sweep resumes them.
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

use super::layout::{
    self, write_record, Overlay, RunLock, StudyRecord, StudyRun, SweepRecord, SweepStatus,
};
use super::profile::{self, Override, Profile};
use super::run::{self, git_revision, RunOptions};
use super::{Experiment, InitSpec, SourceOpener};
use crate::error::{Error, Result};
use crate::train::stop::{self, StopFlag};

/// One run of a sweep.
#[derive(Clone, Debug)]
pub struct Planned {
    pub exp: Experiment,
    /// The replicate it belongs to (`None`: a sweep without seeds).
    pub seed: Option<u64>,
    /// The experiment file, as the sweep found it (the merged text it runs with is `exp.text`).
    pub file: PathBuf,
    /// Keys ([`Planned::key`]) of the runs of this sweep it starts from.
    pub deps: Vec<String>,
    /// 0 for runs without dependencies in the sweep, else 1 + the deepest dependency's level.
    pub level: usize,
}

impl Planned {
    /// Identifies the run within the sweep: `seed-S/NAME`, or `NAME` without seeds.
    pub fn key(&self) -> String {
        run_key(self.seed, &self.exp.name)
    }
}

fn run_key(seed: Option<u64>, name: &str) -> String {
    match seed {
        Some(s) => format!("{}/{name}", layout::seed_folder(s)),
        None => name.to_string(),
    }
}

/// The replicates of a sweep.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Seeds {
    /// Every seed of the study (empty: no replicates, the experiments' own seeds, run
    /// directories `OUTPUT/NAME`).
    pub seeds: Vec<u64>,
    /// Plan only these of them (all if empty): a SLURM array task runs one seed while the
    /// study's seed list still places a shared baseline.
    pub only: Vec<u64>,
    /// Baselines run once, for the first seed; every seed's fine-tunings start from them.
    pub share_baseline: bool,
}

impl Seeds {
    /// The profile's seeds, or `flag` (`--seeds`) when given.
    pub fn from_profile(profile: &Profile, flag: Option<Vec<u64>>) -> Result<Seeds> {
        let seeds = flag.or_else(|| profile.seeds.clone()).unwrap_or_default();
        if !seeds.is_empty() {
            profile::check_seeds(&seeds)
                .map_err(|m| Error::InvalidArgument(format!("--seeds: {m}")))?;
        }
        Ok(Seeds {
            seeds,
            only: Vec::new(),
            share_baseline: profile.share_baseline,
        })
    }
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
    /// Stopped on a signal (checkpoint written; the next sweep resumes it), or not started
    /// because a signal came first: why.
    Interrupted(String),
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
/// (all if empty), and orders them by dependency level, then name. No replicates: see
/// [`plan_seeds`].
pub fn plan(
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    only: &[String],
) -> Result<Vec<Planned>> {
    plan_seeds(dir, profile, overrides, only, &Seeds::default())
}

/// Sets `seed = S` and `output = OUTPUT/seed-S` in a merged experiment text.
fn with_seed(file: &Path, text: &str, seed: u64) -> Result<String> {
    let mut table: toml::Table = toml::from_str(text).map_err(|e| Error::Toml {
        path: file.to_path_buf(),
        message: e.to_string(),
    })?;
    let output = match table.get("output") {
        None => PathBuf::from(super::DEFAULT_OUTPUT),
        Some(toml::Value::String(s)) => PathBuf::from(s),
        Some(_) => {
            return Err(Error::Config {
                path: file.to_path_buf(),
                field: "output".into(),
                message: "must be a path".into(),
            })
        }
    };
    let output = output.join(layout::seed_folder(seed));
    table.insert("seed".into(), toml::Value::Integer(seed as i64));
    table.insert(
        "output".into(),
        toml::Value::String(output.to_string_lossy().into_owned()),
    );
    let header = match text.lines().next() {
        Some(l) if l.starts_with("# ") => l.to_string(),
        _ => format!("# {}", file.display()),
    };
    Ok(format!(
        "{header}, seed {seed}\n{}",
        toml::to_string(&table).expect("a TOML table serialises")
    ))
}

/// [`plan`] with replicates: with `seeds.seeds` empty as [`plan`]; else every experiment once
/// per seed `S` (of `seeds.only`, if given), with `seed = S` and its run directory in
/// `OUTPUT/seed-S/NAME`. Within a seed every fine-tuning starts from that seed's baseline
/// (with `share_baseline`: the first seed's, and baselines are planned for the first seed
/// only) and sees the data in the order of seed `S` (the data order depends on the seed and
/// the data set, never on the kernel).
pub fn plan_seeds(
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    only: &[String],
    seeds: &Seeds,
) -> Result<Vec<Planned>> {
    let selected = read_selected(dir, profile, overrides, only)?;
    for s in &seeds.only {
        if !seeds.seeds.contains(s) {
            return Err(Error::InvalidArgument(format!(
                "seed {s} is not one of the sweep's seeds ({:?})",
                seeds.seeds
            )));
        }
    }
    // (run, its dependency's key if that run is in the plan or planned for another seed).
    let mut all: Vec<(Planned, Option<String>)> = Vec::new();
    let replicates: Vec<Option<u64>> = if seeds.seeds.is_empty() {
        vec![None]
    } else {
        seeds.seeds.iter().map(|s| Some(*s)).collect()
    };
    for &seed in &replicates {
        if let Some(s) = seed {
            if !seeds.only.is_empty() && !seeds.only.contains(&s) {
                continue;
            }
        }
        for (file, merged, exp) in &selected {
            all.extend(replicate(file, merged, exp, seed, seeds)?);
        }
    }
    order_by_level(dir, all)
}

/// Reads, merges and resolves every experiment of `dir` and keeps those matching one of
/// `only` (all if empty; an exact name selects that run only): `(file, merged text,
/// experiment)`. Two experiments of one name, or nothing selected, is an error.
fn read_selected(
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    only: &[String],
) -> Result<Vec<(PathBuf, String, Experiment)>> {
    let mut base = Vec::new();
    for file in experiment_files(dir)? {
        let text = std::fs::read_to_string(&file).map_err(|e| Error::io(&file, e))?;
        let merged = profile::apply(&file, &text, profile, overrides)?;
        let exp = super::parse(&merged, &file)?.resolve(&file, &merged)?;
        base.push((file, merged, exp));
    }
    let mut seen = BTreeSet::new();
    for (file, _, exp) in &base {
        if !seen.insert(exp.name.clone()) {
            return Err(Error::Config {
                path: file.clone(),
                field: "name".into(),
                message: format!("`{}` names two experiments of {}", exp.name, dir.display()),
            });
        }
    }
    let selected: Vec<_> = base
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
    Ok(selected)
}

/// The run of one experiment for replicate `seed` (none for a baseline that a later seed
/// shares), with the key of the run it starts from, if it starts from another experiment.
fn replicate(
    file: &Path,
    merged: &str,
    exp: &Experiment,
    seed: Option<u64>,
    seeds: &Seeds,
) -> Result<Option<(Planned, Option<String>)>> {
    let first = seeds.seeds.first().copied();
    let baseline = exp.init.is_none();
    if baseline && seeds.share_baseline && seed.is_some() && seed != first {
        return Ok(None);
    }
    let mut exp = match seed {
        None => exp.clone(),
        Some(s) => {
            let text = with_seed(file, merged, s)?;
            super::parse(&text, file)?.resolve(file, &text)?
        }
    };
    let mut dep = None;
    if let Some(InitSpec::Experiment { name, checkpoints }) = &mut exp.init {
        let from = if seeds.share_baseline { first } else { seed };
        if from != seed {
            // The shared baseline lives in the first seed's folder.
            let output = exp.output.parent().unwrap_or(&exp.output).to_path_buf();
            *checkpoints = layout::ResultsDir::new(output)
                .run_dir(from, name)
                .checkpoints();
        }
        dep = Some(run_key(from, name));
    }
    let planned = Planned {
        exp,
        seed,
        file: file.to_path_buf(),
        deps: Vec::new(),
        level: 0,
    };
    Ok(Some((planned, dep)))
}

/// Keeps the dependencies that are runs of the plan, gives each run its level, and sorts by
/// level, seed and name; a cycle among the experiments of `dir` is an error.
fn order_by_level(dir: &Path, all: Vec<(Planned, Option<String>)>) -> Result<Vec<Planned>> {
    let keys: BTreeSet<String> = all.iter().map(|(p, _)| p.key()).collect();
    let mut out: Vec<Planned> = all
        .into_iter()
        .map(|(mut p, dep)| {
            p.deps = dep.into_iter().filter(|d| keys.contains(d)).collect();
            p
        })
        .collect();
    // Levels by repeated relaxation; more rounds than runs means a cycle.
    let mut level: BTreeMap<String, usize> = keys.iter().map(|n| (n.clone(), 0)).collect();
    for round in 0..=keys.len() {
        let mut changed = false;
        for p in &out {
            let l = p.deps.iter().map(|d| level[d] + 1).max().unwrap_or(0);
            if l != level[&p.key()] {
                level.insert(p.key(), l);
                changed = true;
            }
        }
        if !changed {
            break;
        }
        if round == keys.len() {
            return Err(Error::InvalidArgument(format!(
                "the experiments of {} start from each other in a cycle",
                dir.display()
            )));
        }
    }
    for p in &mut out {
        p.level = level[&p.key()];
    }
    out.sort_by(|a, b| (a.level, a.seed, &a.exp.name).cmp(&(b.level, b.seed, &b.exp.name)));
    Ok(out)
}

/// The record of a profile and overrides, as [`StudyRecord`] and [`SweepRecord`] store them.
fn overlay(profile: &Profile, overrides: &[Override]) -> Overlay {
    Overlay {
        profile: profile.name.clone(),
        profile_file: profile.file.clone(),
        overrides: overrides.iter().map(Override::to_string).collect(),
    }
}

/// The `study.json` record of a plan.
pub fn study_record(
    dir: &Path,
    plan: &[Planned],
    profile: &Profile,
    overrides: &[Override],
    seeds: &Seeds,
) -> StudyRecord {
    StudyRecord {
        dir: dir.to_path_buf(),
        overlay: overlay(profile, overrides),
        seeds: seeds.seeds.clone(),
        share_baseline: seeds.share_baseline,
        git: git_revision(),
        runs: plan
            .iter()
            .map(|p| StudyRun {
                name: p.exp.name.clone(),
                seed: p.seed,
                dir: PathBuf::from(p.key()),
                level: p.level,
                depends_on: p.deps.clone(),
            })
            .collect(),
    }
}

/// The results folder of a plan: the output folder its run directories are in (above the
/// `seed-S/` folders), if all of them share one.
pub fn results_dir(plan: &[Planned]) -> Option<PathBuf> {
    let dirs: BTreeSet<PathBuf> = plan
        .iter()
        .map(|p| match p.seed {
            Some(_) => p.exp.output.parent().unwrap_or(&p.exp.output).to_path_buf(),
            None => p.exp.output.clone(),
        })
        .collect();
    (dirs.len() == 1).then(|| dirs.into_iter().next().expect("one"))
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

/// `Err` if the run directory holds another configuration than `exp.text`.
fn check_same_config(exp: &Experiment) -> Result<()> {
    let stored = run::run_dir(exp).experiment_toml();
    let old = match std::fs::read_to_string(&stored) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(&stored, e)),
    };
    let parse = |t: &str| toml::from_str::<toml::Table>(t).ok();
    if parse(&old) != parse(&exp.text) {
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
    /// When set, the runs in progress stop after their step (checkpoint written) and no other
    /// run starts ([`StopFlag::process`] on the command line, where signals set it).
    pub stop: StopFlag,
}

/// Runs `p` holding its lock (taken first: a run another process holds fails at once and its
/// records are left alone).
fn run_one(p: &Planned, opts: &SweepOptions<'_>) -> Outcome {
    let lock = match run::run_dir(&p.exp).lock() {
        Ok(l) => l,
        Err(e) => return Outcome::Failed(cause_chain(&e)),
    };
    let outcome = run_locked(p, opts, &lock).unwrap_or_else(|e| {
        if e.is_interrupted() {
            Outcome::Interrupted(e.to_string())
        } else {
            Outcome::Failed(cause_chain(&e))
        }
    });
    match record(p, opts, &outcome, &lock) {
        Ok(()) => outcome,
        // A full disk refuses sweep.json too: keep the run's own error first.
        Err(e) => match outcome {
            Outcome::Failed(first) => Outcome::Failed(format!(
                "{first}; and cannot write sweep.json: {}",
                cause_chain(&e)
            )),
            _ => Outcome::Failed(format!("cannot write sweep.json: {}", cause_chain(&e))),
        },
    }
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
    check_same_config(exp)?;
    let before = state(exp)?;
    if before == State::Complete {
        return Ok(Outcome::Skipped);
    }
    let ropts = RunOptions {
        resume: before == State::Interrupted,
        progress: false,
        verbose: false,
        opener: opts.opener,
        stop: opts.stop,
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
        Outcome::Interrupted(e) => (SweepStatus::Interrupted, None, None, Some(e.clone())),
    };
    let doc = SweepRecord {
        experiment: p.exp.name.clone(),
        file: p.file.clone(),
        overlay: overlay(opts.profile, opts.overrides),
        seed: p.seed,
        level: p.level,
        depends_on: p.deps.clone(),
        git: git_revision(),
        status,
        action,
        seconds,
        finished_unix: seconds.map(|_| layout::unix_now()),
        error,
        experiment_text: p.exp.text.clone(),
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
                    bar.set_message(p.key());
                    // After a stop request only complete runs go on (to be skipped).
                    let stopped = opts
                        .stop
                        .requested()
                        .filter(|_| state(&p.exp).ok() != Some(State::Complete))
                        .map(|s| format!("not started: {} came first", stop::signal_name(s)));
                    let outcome = match (stopped, blocked) {
                        (Some(why), _) => Outcome::Interrupted(why),
                        (None, Some(b)) => record_blocked(p, opts, b),
                        (None, None) => run_one(p, opts),
                    };
                    let line = match &outcome {
                        Outcome::Skipped => "complete, skipped".to_string(),
                        Outcome::Done { action, seconds } => {
                            let timing = run::run_dir(&p.exp)
                                .summary_if_any()
                                .ok()
                                .flatten()
                                .map(|s| format!(" ({})", s.timing.describe()))
                                .unwrap_or_default();
                            format!("{action}: {seconds:.1} s{timing}")
                        }
                        Outcome::Failed(e) => format!("FAILED: {e}"),
                        Outcome::Blocked(e) => format!("blocked: {e}"),
                        Outcome::Interrupted(e) => format!("interrupted: {e}"),
                    };
                    say(&bar, format!("{}: {line}", p.key()));
                    bar.inc(1);
                    outcomes.lock().expect("outcomes").insert(p.key(), outcome);
                });
            }
        });
    }
    bar.finish_and_clear();
    let mut done = outcomes.into_inner().expect("outcomes");
    plan.iter()
        .map(|p| {
            let o = done.remove(&p.key()).expect("every run has an outcome");
            (p.key(), o)
        })
        .collect()
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
