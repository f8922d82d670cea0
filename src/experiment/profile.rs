//! Profiles and command-line overrides: TOML overlays merged over an experiment file's text
//! before it is parsed, so one set of experiment files serves several settings.
//!
//! A profile file has up to three overlay tables in the experiment schema, and the settings
//! of the sweep itself:
//!
//! ```toml
//! seeds = [0, 1, 2]           # replicates (`calibconv sweep --seeds` overrides): each seed
//!                             # runs the whole sweep in OUTPUT/seed-S/ (see experiment::sweep)
//! share_baseline = false      # true: baselines run once (the first seed) and every seed's
//!                             # fine-tunings start from them
//! [slurm]                     # resources of `--emit-slurm` job arrays (see experiment::slurm)
//! cpus_per_task = 1
//! time = "00:30:00"
//! [all]                       # over every experiment
//! data_root = "data/synth"
//! input = { width = 128, padding = [0, 14] }
//! [baseline]                  # over experiments without `model.init`
//! train = { steps = 240 }
//! [finetune]                  # over experiments with `model.init`
//! train = { steps = 80 }
//! ```
//!
//! Merging is key by key: tables merge recursively, any other value (arrays included) replaces
//! the one written. Keys that exclude each other (`epochs` / `steps`, `experiment` /
//! `checkpoint`, `dataset` / `toy`) are one choice: setting one removes the other.
//! `--set KEY=VALUE` overrides (dotted keys, TOML values, strings unquoted) apply last.

use std::path::{Path, PathBuf};

use serde::Serialize;
use toml::{Table, Value};

use crate::error::{Error, Result};

/// Keys that exclude each other within one table.
const EXCLUSIVE: [(&str, &str); 3] = [
    ("epochs", "steps"),
    ("experiment", "checkpoint"),
    ("dataset", "toy"),
];

/// A profile: overlays by role.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Profile {
    /// The profile's name (its file stem), or empty for none.
    pub name: String,
    pub file: Option<PathBuf>,
    pub all: Table,
    pub baseline: Table,
    pub finetune: Table,
    /// Replicate seeds (`None`: no replicates, the experiments' own seeds).
    pub seeds: Option<Vec<u64>>,
    /// One baseline for every seed (in the first seed's folder).
    pub share_baseline: bool,
    /// The `[slurm]` table, as written (resolved by [`super::slurm::SlurmSpec`]).
    pub slurm: Table,
}

/// One `--set KEY=VALUE`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Override {
    /// Dotted key, `optimizer.lr`.
    pub key: String,
    pub value: Value,
}

impl std::str::FromStr for Override {
    type Err = Error;
    /// `KEY=VALUE`; VALUE is read as TOML (`1e-4`, `true`, `[0, 14]`, `"x"`), else a string.
    fn from_str(s: &str) -> Result<Override> {
        let (key, value) = s.split_once('=').ok_or_else(|| {
            Error::InvalidArgument(format!(
                "--set `{s}`: expected KEY=VALUE (optimizer.lr=1e-4)"
            ))
        })?;
        let key = key.trim();
        if key.is_empty() || key.split('.').any(str::is_empty) {
            return Err(Error::InvalidArgument(format!(
                "--set `{s}`: bad key `{key}`"
            )));
        }
        let value = value.trim();
        let value = toml::from_str::<Table>(&format!("v = {value}"))
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| Value::String(value.to_string()));
        Ok(Override {
            key: key.to_string(),
            value,
        })
    }
}

impl std::fmt::Display for Override {
    /// `KEY=VALUE`, the value as TOML: what [`Override::from_str`](std::str::FromStr) reads back.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}={}", self.key, self.value)
    }
}

impl Profile {
    /// Reads `PROFILES_DIR/NAME.toml`.
    pub fn load(file: &Path) -> Result<Profile> {
        let text = std::fs::read_to_string(file).map_err(|e| Error::io(file, e))?;
        let mut table: Table = toml::from_str(&text).map_err(|e| Error::Toml {
            path: file.to_path_buf(),
            message: e.to_string(),
        })?;
        let mut take = |k: &str| -> Result<Table> {
            match table.remove(k) {
                None => Ok(Table::new()),
                Some(Value::Table(t)) => Ok(t),
                Some(_) => Err(Error::Config {
                    path: file.to_path_buf(),
                    field: k.into(),
                    message: "must be a table".into(),
                }),
            }
        };
        let (all, baseline, finetune) = (take("all")?, take("baseline")?, take("finetune")?);
        let slurm = take("slurm")?;
        let bad = |field: &str, message: &str| Error::Config {
            path: file.to_path_buf(),
            field: field.into(),
            message: message.into(),
        };
        let seeds = match table.remove("seeds") {
            None => None,
            Some(Value::Array(a)) => {
                let seeds: Option<Vec<u64>> = a
                    .iter()
                    .map(|v| v.as_integer().and_then(|i| u64::try_from(i).ok()))
                    .collect();
                let seeds = seeds.ok_or_else(|| bad("seeds", "must be non-negative integers"))?;
                check_seeds(&seeds).map_err(|m| bad("seeds", &m))?;
                Some(seeds)
            }
            Some(_) => return Err(bad("seeds", "must be an array of integers, [0, 1, 2]")),
        };
        let share_baseline = match table.remove("share_baseline") {
            None => false,
            Some(Value::Boolean(b)) => b,
            Some(_) => return Err(bad("share_baseline", "must be true or false")),
        };
        if let Some(k) = table.keys().next() {
            return Err(bad(
                k,
                "a profile has only the keys seeds and share_baseline and the tables [all], \
                 [baseline], [finetune] and [slurm]",
            ));
        }
        Ok(Profile {
            name: file
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            file: Some(file.to_path_buf()),
            all,
            baseline,
            finetune,
            seeds,
            share_baseline,
            slurm,
        })
    }
}

/// `Err` (a message) unless `seeds` is non-empty without repeats.
pub fn check_seeds(seeds: &[u64]) -> std::result::Result<(), String> {
    if seeds.is_empty() {
        return Err("give at least one seed".into());
    }
    let mut seen = std::collections::BTreeSet::new();
    if let Some(s) = seeds.iter().find(|s| !seen.insert(**s)) {
        return Err(format!("seed {s} is given twice"));
    }
    Ok(())
}

/// Merges `over` into `base` key by key (see the module docs).
pub fn merge(base: &mut Table, over: &Table) {
    for (k, v) in over {
        for (a, b) in EXCLUSIVE {
            if k == a {
                base.remove(b);
            } else if k == b {
                base.remove(a);
            }
        }
        match (base.get_mut(k), v) {
            (Some(Value::Table(bt)), Value::Table(ot)) => merge(bt, ot),
            _ => {
                base.insert(k.clone(), v.clone());
            }
        }
    }
}

/// Sets dotted `key` of `table` to `value` (creating tables on the way).
pub fn set(table: &mut Table, key: &str, value: Value) {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().expect("non-empty key");
    let mut over = Table::new();
    over.insert(last.to_string(), value);
    for p in parts.into_iter().rev() {
        let mut t = Table::new();
        t.insert(p.to_string(), Value::Table(over));
        over = t;
    }
    merge(table, &over);
}

/// The text of experiment file `path` (`text`) with `profile` and `overrides` applied; the
/// text itself when there is nothing to apply.
pub fn apply(path: &Path, text: &str, profile: &Profile, overrides: &[Override]) -> Result<String> {
    let empty =
        profile.all.is_empty() && profile.baseline.is_empty() && profile.finetune.is_empty();
    if empty && overrides.is_empty() {
        return Ok(text.to_string());
    }
    let mut table: Table = toml::from_str(text).map_err(|e| Error::Toml {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let finetune = table.get("model").and_then(|m| m.get("init")).is_some();
    merge(&mut table, &profile.all);
    merge(
        &mut table,
        if finetune {
            &profile.finetune
        } else {
            &profile.baseline
        },
    );
    for o in overrides {
        set(&mut table, &o.key, o.value.clone());
    }
    let mut header = format!("# {}", path.display());
    if !profile.name.is_empty() {
        header += &format!(" with profile `{}`", profile.name);
    }
    for o in overrides {
        header += &format!(", --set {o}");
    }
    Ok(format!(
        "{header}\n{}",
        toml::to_string(&table).expect("a TOML table serialises")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overlays_merge_key_by_key_and_exclusive_keys_replace_each_other() {
        let text = "name = \"a\"\n[train]\nepochs = 5\nbatch_size = 8\n[model]\npreset = \"classic\"\ninit = { experiment = \"bl\" }\n";
        let profile = Profile {
            name: "q".into(),
            all: toml::from_str("model = { preset = \"tiny\" }").unwrap(),
            baseline: toml::from_str("train = { steps = 1 }").unwrap(),
            finetune: toml::from_str("train = { steps = 7 }").unwrap(),
            ..Default::default()
        };
        let o: Override = "optimizer.lr=1e-4".parse().unwrap();
        let s: Override = "device=cpu".parse().unwrap();
        assert_eq!(s.value, Value::String("cpu".into()));
        let out = apply(Path::new("x.toml"), text, &profile, &[o, s]).unwrap();
        let t: Table = toml::from_str(&out).unwrap();
        assert_eq!(t["train"]["steps"].as_integer(), Some(7));
        assert!(t["train"].get("epochs").is_none());
        assert_eq!(t["train"]["batch_size"].as_integer(), Some(8));
        assert_eq!(t["model"]["preset"].as_str(), Some("tiny"));
        assert_eq!(t["model"]["init"]["experiment"].as_str(), Some("bl"));
        assert_eq!(t["optimizer"]["lr"].as_float(), Some(1e-4));
        assert_eq!(t["device"].as_str(), Some("cpu"));
        assert!(out.starts_with("# x.toml with profile `q`, --set optimizer.lr=0.0001"));
        assert!("nokey".parse::<Override>().is_err());
    }
}
