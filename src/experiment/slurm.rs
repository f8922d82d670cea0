//! SLURM scripts of a sweep (`calibconv sweep DIR --emit-slurm OUT`): one job array per
//! dependency level, chained with `--dependency=afterok`, whose resources come from the
//! profile's `[slurm]` table (and `--slurm-set KEY=VALUE`).
//!
//! ```toml
//! [slurm]
//! partition = "gpu"            # --partition (default: the cluster's)
//! account = "proj"             # --account
//! time = "24:00:00"            # --time
//! cpus_per_task = 8            # --cpus-per-task; also the run's libtorch threads
//! mem = "32G"                  # --mem
//! gres = "gpu:1"               # --gres (absent: no generic resources, e.g. no GPU)
//! signal_seconds = 120         # --signal=B:USR1@S: the warning before the time limit
//! extra = ["--qos=normal"]     # more #SBATCH lines, as written after `#SBATCH `
//! ```
//!
//! Every array task is one run of one replicate: task `i` of `level-K.sbatch` runs
//! `calibconv sweep DIR --profile P [--set ...] [--seeds LIST --only-seed S_i] --only NAME_i`,
//! so skipping, resuming and the run-directory lock work as on one machine. `submit.sh`
//! submits the levels in order; the scripts run as written (`bash OUT/submit.sh`).
//!
//! # Time limits and preemption
//!
//! The tasks are requeueable (`--requeue`, log files appended: `--open-mode=append`) and ask
//! SLURM for SIGUSR1 `signal_seconds` before their time limit (`--signal=B:USR1@S`, default
//! [`DEFAULT_SIGNAL_SECONDS`]; SLURM may send it up to a minute early). The batch script
//! passes SIGUSR1, SIGTERM (preemption, `scancel`) and SIGINT on to calibconv, which finishes
//! its step, writes its checkpoint and exits with status 75
//! ([`crate::train::stop::INTERRUPTED_EXIT`]); on that status alone the script runs `scontrol
//! requeue` of its own array task, which starts again later and resumes exactly where it
//! stopped. Any other failure ends the task as failed and is not requeued. S must leave time
//! for one training step, one checkpoint and the task's start-up; a step that outlasts it is
//! killed at the limit, and the task resumes from its previous checkpoint when run again.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use toml::{Table, Value};

use super::profile::{self, Override, Profile};
use super::sweep::{Planned, Seeds};
use crate::error::{Error, Result};
use crate::io::write_bytes_atomic;

/// The `[slurm]` table, resolved.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlurmSpec {
    pub partition: Option<String>,
    pub account: Option<String>,
    pub time: Option<String>,
    pub cpus_per_task: Option<u32>,
    pub mem: Option<String>,
    pub gres: Option<String>,
    /// Seconds before the time limit at which SLURM sends SIGUSR1 (absent:
    /// [`DEFAULT_SIGNAL_SECONDS`]).
    pub signal_seconds: Option<u32>,
    #[serde(default)]
    pub extra: Vec<String>,
}

/// The warning before the time limit when `[slurm]` has no `signal_seconds`: two minutes, room
/// for a step and a checkpoint of the paper profile's networks on one GPU with a margin.
pub const DEFAULT_SIGNAL_SECONDS: u32 = 120;

/// The most seconds `--signal` accepts (SLURM's limit).
const MAX_SIGNAL_SECONDS: u32 = 65_535;

/// The keys of `[slurm]`.
pub const SLURM_KEYS: [&str; 8] = [
    "partition",
    "account",
    "time",
    "cpus_per_task",
    "mem",
    "gres",
    "signal_seconds",
    "extra",
];

impl SlurmSpec {
    /// The profile's `[slurm]` table with `--slurm-set KEY=VALUE` overrides applied: a
    /// string `extra` adds one line, an array replaces them.
    pub fn resolve(profile: &Profile, sets: &[Override]) -> Result<SlurmSpec> {
        let mut table: Table = profile.slurm.clone();
        for o in sets {
            if !SLURM_KEYS.contains(&o.key.as_str()) {
                let hint = super::suggest::did_you_mean(&o.key, &SLURM_KEYS);
                return Err(Error::InvalidArgument(format!(
                    "--slurm-set {}: unknown key (expected one of {}){hint}",
                    o.key,
                    SLURM_KEYS.join(", ")
                )));
            }
            match (o.key.as_str(), &o.value) {
                ("extra", Value::String(line)) => {
                    let mut lines = match table.remove("extra") {
                        Some(Value::Array(a)) => a,
                        _ => Vec::new(),
                    };
                    lines.push(Value::String(line.clone()));
                    table.insert("extra".into(), Value::Array(lines));
                }
                ("cpus_per_task" | "signal_seconds", v) => {
                    profile::set(&mut table, &o.key, v.clone());
                }
                (_, Value::Integer(i)) => {
                    // `time=60` means minutes to SLURM; keep it a string.
                    profile::set(&mut table, &o.key, Value::String(i.to_string()));
                }
                (_, v) => profile::set(&mut table, &o.key, v.clone()),
            }
        }
        let field = |m: String| Error::Config {
            path: profile
                .file
                .clone()
                .unwrap_or_else(|| PathBuf::from("<no profile>")),
            field: "slurm".into(),
            message: m,
        };
        let spec: SlurmSpec = Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| field(e.message().to_string()))?;
        if spec.cpus_per_task == Some(0) {
            return Err(field("cpus_per_task must be positive".into()));
        }
        if spec
            .signal_seconds
            .is_some_and(|s| s == 0 || s > MAX_SIGNAL_SECONDS)
        {
            return Err(field(format!(
                "signal_seconds must be 1 to {MAX_SIGNAL_SECONDS}"
            )));
        }
        for (k, v) in [
            ("partition", &spec.partition),
            ("account", &spec.account),
            ("time", &spec.time),
            ("mem", &spec.mem),
            ("gres", &spec.gres),
        ] {
            if v.as_ref()
                .is_some_and(|s| s.is_empty() || s.contains(char::is_whitespace))
            {
                return Err(field(format!("{k} must be one word, got {v:?}")));
            }
        }
        Ok(spec)
    }

    /// The `#SBATCH` lines of the resources.
    pub fn directives(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut add = |flag: &str, v: &Option<String>| {
            if let Some(v) = v {
                out.push(format!("#SBATCH --{flag}={v}"));
            }
        };
        add("partition", &self.partition);
        add("account", &self.account);
        add("time", &self.time);
        add("cpus-per-task", &self.cpus_per_task.map(|c| c.to_string()));
        add("mem", &self.mem);
        add("gres", &self.gres);
        out.extend(self.extra.iter().map(|l| format!("#SBATCH {l}")));
        out
    }

    /// The `#SBATCH` lines that make a task survive its time limit and preemption: the warning
    /// signal, requeueable, logs appended across requeues.
    pub fn requeue_directives(&self) -> [String; 3] {
        let s = self.signal_seconds.unwrap_or(DEFAULT_SIGNAL_SECONDS);
        [
            format!("#SBATCH --signal=B:USR1@{s}"),
            "#SBATCH --requeue".into(),
            "#SBATCH --open-mode=append".into(),
        ]
    }
}

fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', "'\\''"))
}

/// The `calibconv sweep` command line every array task runs (before its `--only`): the binary
/// that wrote the scripts (the cluster shares the file system), else `calibconv` from PATH,
/// with the sweep's folder, profile, overrides and seeds.
fn sweep_command(dir: &Path, profile: &Profile, overrides: &[Override], seeds: &Seeds) -> String {
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
        common += &format!(" --set {}", quote(&o.to_string()));
    }
    if !seeds.seeds.is_empty() {
        let list: Vec<String> = seeds.seeds.iter().map(u64::to_string).collect();
        common += &format!(" --seeds {}", list.join(","));
    }
    common
}

/// The `calibconv sweep ... --status` command that shows where the emitted sweep stands (the
/// same binary, folder, profile, overrides, seeds and `--only` patterns).
pub fn status_command(
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    seeds: &Seeds,
    only: &[String],
) -> String {
    let mut cmd = sweep_command(dir, profile, overrides, seeds);
    for o in only {
        cmd += &format!(" --only {}", quote(o));
    }
    cmd + " --status"
}

/// `level-K.sbatch`: one array task per run of dependency level `level`, run from `root`
/// (quoted) with `common` ([`sweep_command`]).
fn level_script(
    level: usize,
    runs: &[&Planned],
    seeds: &Seeds,
    directives: &str,
    root: &str,
    common: &str,
) -> String {
    let names: Vec<&str> = runs.iter().map(|p| p.exp.name.as_str()).collect();
    let seed_line = if seeds.seeds.is_empty() {
        String::new()
    } else {
        let s: Vec<String> = runs
            .iter()
            .map(|p| p.seed.map_or(String::new(), |s| s.to_string()))
            .collect();
        format!("SEEDS=({})\n", s.join(" "))
    };
    let only_seed = if seeds.seeds.is_empty() {
        ""
    } else {
        " --only-seed \"${SEEDS[$SLURM_ARRAY_TASK_ID]}\""
    };
    format!(
        "#!/bin/bash\n\
         #SBATCH --job-name=calibconv-level-{level}\n\
         #SBATCH --array=0-{last}\n\
         {directives}{sep}\
         #SBATCH --output=slurm-%A_%a.out\n\
         # Dependency level {level}: {n} run(s); submit with submit.sh (afterok on level {prev}).\n\
         set -euo pipefail\n\
         {RUN_AND_REQUEUE_HEAD}\
         cd {root}\n\
         RUNS=({runs})\n\
         {seed_line}\
         srun {common}{only_seed} --only \"${{RUNS[$SLURM_ARRAY_TASK_ID]}}\" \
         ${{SLURM_CPUS_PER_TASK:+--threads $SLURM_CPUS_PER_TASK}} -q &\n\
         {RUN_AND_REQUEUE_TAIL}",
        last = names.len() - 1,
        sep = if directives.is_empty() { "" } else { "\n" },
        n = names.len(),
        prev = level.saturating_sub(1),
        runs = names.join(" "),
    )
}

/// At the top of the script (a signal before it would end the shell): the batch shell (the only
/// process SLURM's `B:` signal reaches) passes SIGUSR1, SIGTERM and SIGINT on to srun, which
/// passes them to calibconv; one that comes before srun starts is passed on once it has.
const RUN_AND_REQUEUE_HEAD: &str = "\
# SIGUSR1 (before the time limit), SIGTERM (preemption, scancel) and SIGINT (sent on as SIGTERM:
# srun keeps SIGINT for itself) go to calibconv, which finishes its step, writes its checkpoint
# and exits with status 75.
child=\"\"
stop=\"\"
pass_on() { stop=$1; if [ -n \"$child\" ]; then kill -s \"$1\" \"$child\" 2>/dev/null || true; fi; }
trap 'pass_on USR1' USR1
trap 'pass_on TERM' TERM
trap 'pass_on TERM' INT
";

/// After the task's `srun ... &`: waits for it (a trapped signal interrupts `wait`), then on
/// status 75, and on it alone, requeues this array task.
const RUN_AND_REQUEUE_TAIL: &str = "\
child=$!
if [ -n \"$stop\" ]; then kill -s \"$stop\" \"$child\" 2>/dev/null || true; fi
while kill -0 \"$child\" 2>/dev/null; do wait \"$child\" || true; done
status=0
wait \"$child\" || status=$?
if [ \"$status\" = 75 ]; then
  task=\"${SLURM_ARRAY_JOB_ID:-$SLURM_JOB_ID}${SLURM_ARRAY_TASK_ID:+_$SLURM_ARRAY_TASK_ID}\"
  echo \"calibconv stopped with its checkpoint written (restart ${SLURM_RESTART_COUNT:-0}); requeueing $task\"
  scontrol requeue \"$task\"
fi
exit \"$status\"
";

/// Writes `level-K.sbatch` (one job array per dependency level) and `submit.sh` into `out`
/// for `plan` (planned with the `--only` patterns `only`); returns the files written.
#[allow(clippy::too_many_arguments)]
pub fn emit_slurm(
    plan: &[Planned],
    dir: &Path,
    profile: &Profile,
    overrides: &[Override],
    seeds: &Seeds,
    only: &[String],
    spec: &SlurmSpec,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let common = sweep_command(dir, profile, overrides, seeds);
    let root = std::env::current_dir().map_err(|e| Error::io(Path::new("."), e))?;
    let root = quote(&root.display().to_string());
    let max_level = plan.iter().map(|p| p.level).max().unwrap_or(0);
    let mut files = Vec::new();
    let mut submit = String::from(
        "#!/bin/bash\n# Submits the sweep's job arrays, each level after the one before succeeded.\n\
         set -euo pipefail\ncd \"$(dirname \"$0\")\"\n",
    );
    let directives = spec
        .directives()
        .into_iter()
        .chain(spec.requeue_directives())
        .collect::<Vec<_>>()
        .join("\n");
    for level in 0..=max_level {
        let runs: Vec<&Planned> = plan.iter().filter(|p| p.level == level).collect();
        let file = out.join(format!("level-{level}.sbatch"));
        let text = level_script(level, &runs, seeds, &directives, &root, &common);
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
    submit += &format!(
        "echo {}\n",
        quote(&format!(
            "watch with: {}",
            status_command(dir, profile, overrides, seeds, only)
        ))
    );
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
    fn slurm_set_overrides_the_profile_and_unknown_keys_are_named() {
        let profile = Profile {
            slurm: toml::from_str("cpus_per_task = 1\ntime = \"00:30:00\"\nextra = [\"--qos=a\"]")
                .unwrap(),
            ..Default::default()
        };
        let sets: Vec<Override> = ["gres=gpu:1", "cpus_per_task=4", "extra=--exclusive"]
            .iter()
            .map(|s| s.parse().unwrap())
            .collect();
        let spec = SlurmSpec::resolve(&profile, &sets).unwrap();
        assert_eq!(
            spec.directives(),
            [
                "#SBATCH --time=00:30:00",
                "#SBATCH --cpus-per-task=4",
                "#SBATCH --gres=gpu:1",
                "#SBATCH --qos=a",
                "#SBATCH --exclusive"
            ]
        );
        let plain = SlurmSpec::resolve(&Profile::default(), &[]).unwrap();
        assert!(plain.directives().is_empty());
        let e = SlurmSpec::resolve(&profile, &["gress=gpu:1".parse().unwrap()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("did you mean `gres`"), "{e}");
        let bad = Profile {
            slurm: toml::from_str("cpus = 2").unwrap(),
            ..Default::default()
        };
        assert!(SlurmSpec::resolve(&bad, &[]).is_err());
    }
}
