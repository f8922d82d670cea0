//! `calibconv report RESULTS [--out DIR]`.

use anyhow::{Context, Result};

use crate::cli::ReportArgs;

pub fn run(args: ReportArgs) -> Result<()> {
    let out = args.out.clone().unwrap_or_else(|| args.results.clone());
    let written = calibconv::report::results::write_report(&args.results, &out)
        .with_context(|| format!("cannot report on {}", args.results.display()))?;
    for f in &written {
        println!("wrote {}", f.display());
    }
    println!("report: {}", out.join("REPORT.md").display());
    Ok(())
}
