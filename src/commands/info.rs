//! `calibconv info [--json]`: what this build runs on.

use anyhow::Result;

use calibconv::device::RuntimeInfo;

use crate::cli::InfoArgs;

pub fn run(args: InfoArgs) -> Result<()> {
    let info = RuntimeInfo::read();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&info)?);
    } else {
        for line in info.lines() {
            println!("{line}");
        }
    }
    Ok(())
}
