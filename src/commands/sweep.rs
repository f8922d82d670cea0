//! `calibconv sweep DIR [--profile P] [--seeds S,..] [--only PATTERN] [--jobs N] [--set K=V]
//! [--emit-slurm D [--slurm-set K=V] | --status | --dry-run]`.

use std::io::IsTerminal;
use std::path::Path;

use anyhow::{bail, Context, Result};

use calibconv::experiment::layout::{write_record, ResultsDir};
use calibconv::experiment::profile::{Override, Profile};
use calibconv::experiment::slurm::{emit_slurm, status_command, SlurmSpec};
use calibconv::experiment::status;
use calibconv::experiment::sweep::{self, Outcome, Planned, Seeds, SweepOptions};
use calibconv::experiment::DefaultOpener;
use calibconv::train::stop::{self, StopFlag};

use crate::cli::SweepArgs;

pub fn run(args: SweepArgs) -> Result<()> {
    let profile = match &args.profile {
        Some(name) => sweep::find_profile(&args.dir, name)?,
        None => Profile::default(),
    };
    let overrides = parse_overrides(&args.set)?;
    if let Some(t) = args.threads {
        anyhow::ensure!(t > 0, "--threads must be positive");
        tch::set_num_threads(t);
    }
    let mut seeds = Seeds::from_profile(&profile, args.seeds.clone())?;
    if !args.only_seed.is_empty() {
        anyhow::ensure!(
            !seeds.seeds.is_empty(),
            "--only-seed needs seeds (--seeds or the profile's `seeds`)"
        );
        seeds.only = args.only_seed.clone();
    }
    let plan = sweep::plan_seeds(&args.dir, &profile, &overrides, &args.only, &seeds)
        .with_context(|| format!("cannot plan the sweep of {}", args.dir.display()))?;
    if args.status {
        print!("{}", status::table(&plan));
        return Ok(());
    }
    // The study's record, for a sweep of the whole study (not one task of it).
    let whole = args.only.is_empty() && args.only_seed.is_empty() && !args.dry_run;
    let write_study = || -> Result<()> {
        if let (true, Some(results)) = (whole, sweep::results_dir(&plan)) {
            let file = ResultsDir::new(results).study_json();
            let record = sweep::study_record(&args.dir, &plan, &profile, &overrides, &seeds);
            write_record(&file, &record)?;
        }
        Ok(())
    };
    let slurm_sets = parse_overrides(&args.slurm_set)?;
    anyhow::ensure!(
        slurm_sets.is_empty() || args.emit_slurm.is_some(),
        "--slurm-set applies to --emit-slurm"
    );
    if let Some(out) = &args.emit_slurm {
        let spec = SlurmSpec::resolve(&profile, &slurm_sets)?;
        let files = emit_slurm(
            &plan, &args.dir, &profile, &overrides, &seeds, &args.only, &spec, out,
        )
        .with_context(|| format!("cannot write SLURM scripts to {}", out.display()))?;
        write_study()?;
        for f in &files {
            println!("wrote {}", f.display());
        }
        println!("submit with: bash {}", out.join("submit.sh").display());
        println!(
            "watch with: {}",
            status_command(&args.dir, &profile, &overrides, &seeds, &args.only)
        );
        return Ok(());
    }
    print_plan(&plan)?;
    if args.dry_run {
        return Ok(());
    }
    announce_devices(&plan)?;
    write_study()?;
    // SIGUSR1, SIGTERM, SIGINT: the runs in progress finish their step and write their
    // checkpoint, no other run starts, and the sweep exits with status 75.
    stop::install().context("cannot install the signal handlers")?;
    let start = std::time::Instant::now();
    let outcomes = sweep::run_sweep(
        &plan,
        &SweepOptions {
            profile: &profile,
            overrides: &overrides,
            jobs: args.jobs,
            progress: !args.quiet && std::io::stderr().is_terminal(),
            opener: &DefaultOpener,
            stop: StopFlag::process(),
        },
    );
    summarise(&args.dir, &plan, &outcomes, start.elapsed().as_secs_f64())
}

/// `KEY=VALUE` overrides (`--set`, `--slurm-set`).
fn parse_overrides(sets: &[String]) -> Result<Vec<Override>> {
    Ok(sets
        .iter()
        .map(|s| s.parse::<Override>())
        .collect::<calibconv::error::Result<Vec<_>>>()?)
}

/// The plan on stderr: a line per run with its level, state and dependencies.
fn print_plan(plan: &[Planned]) -> Result<()> {
    for p in plan {
        eprintln!(
            "level {} {:<44} {:?}{}",
            p.level,
            p.key(),
            sweep::state(&p.exp)?,
            if p.deps.is_empty() {
                String::new()
            } else {
                format!(" (after {})", p.deps.join(", "))
            }
        );
    }
    Ok(())
}

/// Checks every run's `device` before any work (`cuda` without CUDA is an error naming the
/// file), and says on stderr what each distinct setting resolved to.
fn announce_devices(plan: &[Planned]) -> Result<()> {
    let mut seen = std::collections::BTreeMap::new();
    for p in plan {
        let device = p.exp.device()?;
        seen.entry(p.exp.device.clone()).or_insert((device, 0)).1 += 1;
    }
    for (spec, (device, runs)) in seen {
        eprintln!(
            "device = \"{spec}\" -> {} ({runs} run(s))",
            calibconv::device::describe(device)
        );
    }
    Ok(())
}

/// The sweep's counts and where its results are; an error naming the runs that failed.
fn summarise(
    dir: &Path,
    plan: &[Planned],
    outcomes: &[(String, Outcome)],
    seconds: f64,
) -> Result<()> {
    let failed: Vec<_> = outcomes.iter().filter(|(_, o)| o.is_failure()).collect();
    let ran = outcomes
        .iter()
        .filter(|(_, o)| matches!(o, Outcome::Done { .. }))
        .count();
    println!(
        "sweep of {}: {} run(s), {ran} ran, {} skipped (complete), {} failed, in {:.1} s",
        dir.display(),
        outcomes.len(),
        outcomes
            .iter()
            .filter(|(_, o)| *o == Outcome::Skipped)
            .count(),
        failed.len(),
        seconds
    );
    if let Some(r) = sweep::results_dir(plan) {
        println!("results in {}", r.display());
    }
    if !failed.is_empty() {
        for (name, o) in &failed {
            match o {
                Outcome::Failed(e) => eprintln!("FAILED {name}: {e}"),
                Outcome::Blocked(e) => eprintln!("BLOCKED {name}: {e}"),
                _ => {}
            }
        }
        bail!("{} of {} run(s) failed", failed.len(), outcomes.len());
    }
    let interrupted: Vec<_> = outcomes
        .iter()
        .filter(|(_, o)| matches!(o, Outcome::Interrupted(_)))
        .collect();
    if !interrupted.is_empty() {
        for (name, o) in &interrupted {
            if let Outcome::Interrupted(e) = o {
                eprintln!("INTERRUPTED {name}: {e}");
            }
        }
        let signal = StopFlag::process()
            .requested()
            .map_or_else(|| "a signal".to_string(), stop::signal_name);
        // The library's error, so that the binary exits with the status SLURM scripts requeue.
        return Err(calibconv::Error::Interrupted {
            signal,
            what: format!(
                "with {} of {} run(s) not finished",
                interrupted.len(),
                outcomes.len()
            ),
        }
        .into());
    }
    Ok(())
}
