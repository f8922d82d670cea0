//! `calibconv export CHECKPOINT --out state_dict.safetensors`: a calibconv checkpoint as a
//! PyTorch `state_dict` (milesial/Pytorch-UNet names, `num_batches_tracked` included).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use calibconv::train::pytorch;

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// calibconv checkpoint (e.g. runs/NAME/checkpoints/best.safetensors).
    pub checkpoint: PathBuf,
    /// Output safetensors file, written atomically.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: ExportArgs) -> Result<()> {
    let e = pytorch::export(&args.checkpoint, &args.out)
        .with_context(|| format!("cannot export {}", args.checkpoint.display()))?;
    let a = &e.architecture;
    println!(
        "{}: {} keys; in PyTorch: UNet(n_channels={}, n_classes={}, bilinear={}) with base {} \
         and depth {}, then model.load_state_dict(safetensors.torch.load_file(\"{}\"), \
         strict=True)",
        args.out.display(),
        e.keys,
        a.in_channels,
        a.classes,
        if a.variant == "bilinear" {
            "True"
        } else {
            "False"
        },
        a.base,
        a.depth,
        args.out.display()
    );
    if (a.base, a.depth) != (64, 4) {
        eprintln!(
            "note: milesial's UNet class has base 64 and depth 4; this network needs the same \
             blocks with other widths (e.g. tools/reference_unet.py's `base`)"
        );
    }
    if e.kernel != "standard" {
        eprintln!(
            "note: trained with {} kernels; a PyTorch network with standard convolutions \
             computes something else with these weights",
            e.kernel
        );
    }
    Ok(())
}
