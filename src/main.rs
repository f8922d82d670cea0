//! The `calibconv` binary: parse, run, print errors with their cause chain.

mod cli;
mod commands;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = cli::Cli::parse();
    match commands::run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            // Stopped on a signal with its checkpoint written: the status SLURM scripts requeue.
            let interrupted = e.chain().any(|c| {
                c.downcast_ref::<calibconv::Error>()
                    .is_some_and(calibconv::Error::is_interrupted)
            });
            if interrupted {
                ExitCode::from(calibconv::train::stop::INTERRUPTED_EXIT)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}
