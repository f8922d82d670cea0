//! `calibconv sweep DIR [--profile P] [--only PATTERN] [--jobs N] [--set K=V] [--emit-slurm D]`.

use std::io::IsTerminal;

use anyhow::{bail, Context, Result};

use calibconv::experiment::profile::{Override, Profile};
use calibconv::experiment::sweep::{self, Outcome, SweepOptions};
use calibconv::experiment::DefaultOpener;

use crate::cli::SweepArgs;

pub fn run(args: SweepArgs) -> Result<()> {
    let profile = match &args.profile {
        Some(name) => sweep::find_profile(&args.dir, name)?,
        None => Profile::default(),
    };
    let overrides = args
        .set
        .iter()
        .map(|s| s.parse::<Override>())
        .collect::<calibconv::error::Result<Vec<_>>>()?;
    if let Some(t) = args.threads {
        anyhow::ensure!(t > 0, "--threads must be positive");
        tch::set_num_threads(t);
    }
    let plan = sweep::plan(&args.dir, &profile, &overrides, &args.only)
        .with_context(|| format!("cannot plan the sweep of {}", args.dir.display()))?;
    if let Some(out) = &args.emit_slurm {
        let files = sweep::emit_slurm(&plan, &args.dir, &profile, &overrides, out)
            .with_context(|| format!("cannot write SLURM scripts to {}", out.display()))?;
        for f in &files {
            println!("wrote {}", f.display());
        }
        println!("submit with: {}", out.join("submit.sh").display());
        return Ok(());
    }
    for p in &plan {
        eprintln!(
            "level {} {:<36} {:?}{}",
            p.level,
            p.exp.name,
            sweep::state(&p.exp)?,
            if p.deps.is_empty() {
                String::new()
            } else {
                format!(" (after {})", p.deps.join(", "))
            }
        );
    }
    if args.dry_run {
        return Ok(());
    }
    let start = std::time::Instant::now();
    let outcomes = sweep::run_sweep(
        &plan,
        &SweepOptions {
            profile: &profile,
            overrides: &overrides,
            jobs: args.jobs,
            progress: !args.quiet && std::io::stderr().is_terminal(),
            opener: &DefaultOpener,
        },
    );
    let failed: Vec<_> = outcomes.iter().filter(|(_, o)| o.is_failure()).collect();
    let ran = outcomes
        .iter()
        .filter(|(_, o)| matches!(o, Outcome::Done { .. }))
        .count();
    println!(
        "sweep of {}: {} run(s), {ran} ran, {} skipped (complete), {} failed, in {:.1} s",
        args.dir.display(),
        outcomes.len(),
        outcomes
            .iter()
            .filter(|(_, o)| *o == Outcome::Skipped)
            .count(),
        failed.len(),
        start.elapsed().as_secs_f64()
    );
    if let Some(p) = plan.first() {
        println!("results in {}", p.exp.output.display());
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
    Ok(())
}
