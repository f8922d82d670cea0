//! `calibconv train EXPERIMENT.toml [--resume]`: train, then evaluate, in the run directory.

use anyhow::{Context, Result};

use calibconv::experiment;
use calibconv::train::stop::{self, StopFlag};

use crate::cli::TrainArgs;

pub fn run(args: TrainArgs) -> Result<()> {
    let exp = args.run.load()?;
    // SIGUSR1, SIGTERM, SIGINT: finish the step, write the checkpoint, exit with status 75.
    stop::install().context("cannot install the signal handlers")?;
    let opts = args.run.options(args.resume, StopFlag::process());
    let outcome =
        experiment::train(&exp, &opts).with_context(|| format!("training {} failed", exp.name))?;
    let s = &outcome.summary;
    println!(
        "{}: {} steps, loss {:.4} -> {:.4}, {:.1} images/s{}; run directory {}",
        exp.name,
        s.steps,
        s.first_loss,
        s.last_loss,
        s.images_per_s,
        s.best
            .map(|(m, v, step)| format!(", best {m} {v:.4} at step {step}"))
            .unwrap_or_default(),
        exp.run_dir.display()
    );
    Ok(())
}
