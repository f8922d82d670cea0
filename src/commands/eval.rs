//! `calibconv eval EXPERIMENT.toml [--checkpoint P] [--only NAME]`: run the experiment's
//! evaluations on a checkpoint.

use anyhow::{bail, Context, Result};

use calibconv::experiment;
use calibconv::train::stop::StopFlag;

use crate::cli::EvalArgs;

pub fn run(args: EvalArgs) -> Result<()> {
    let exp = args.run.load()?;
    if exp.evals.is_empty() {
        bail!(
            "{} has no evaluations: add [[eval]] entries or a data.test source",
            args.run.experiment.display()
        );
    }
    // No signal handlers here: Ctrl-C ends an evaluation at once (it writes no state).
    let opts = args.run.options(false, StopFlag::detached());
    let outcomes = experiment::evaluate(&exp, args.checkpoint.as_deref(), &args.only, &opts)
        .with_context(|| format!("evaluating {} failed", exp.name))?;
    for o in &outcomes {
        let metrics: Vec<String> = o
            .evaluation
            .metrics
            .iter()
            .map(|(m, v)| format!("{m} {v:.4}"))
            .collect();
        // What these numbers are: metrics.json also holds depth's per-image convention.
        let convention = match o.evaluation.head.task_name() {
            "depth" => "pooled over the valid pixels of the set; per-image values in metrics.json",
            _ => "one confusion matrix over the set",
        };
        println!(
            "{}: {} ({convention}) -> {}",
            o.name,
            metrics.join(", "),
            o.dir.display()
        );
    }
    Ok(())
}
