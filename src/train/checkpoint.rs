//! Checkpoints: safetensors files with metadata, written atomically.
//!
//! A model checkpoint holds every variable of the network's [`VarStore`] under its own name
//! (`inc.double_conv.0.weight`, ..., BatchNorm running statistics included), in the variable's
//! dtype, plus string metadata: `format` (= [`FORMAT`]), `step`, `kernel`, `task`, and
//! `calibconv`: the whole [`CheckpointInfo`] as JSON (model config, input size, kernel kind,
//! camera file and text, step, epoch position, metrics, git revision). Any safetensors reader
//! shows them (`safetensors.safe_open(path, "pt").metadata()` in Python).
//!
//! Loading compares names and shapes first and reports *every* mismatch (missing, unexpected,
//! wrong shape; the first one named first) before touching a variable, so a wrong checkpoint
//! never half-loads. Files without calibconv metadata load too (a PyTorch `state_dict` saved
//! with `safetensors.torch.save_file` or converted by `tools/convert_checkpoint.py`, e.g.
//! milesial/Pytorch-UNet weights): names map by the one table in [`super::pytorch`] (BatchNorm
//! `num_batches_tracked` is dropped, tch has no such buffer; every other name must match), and
//! the converter's `architecture` record, if any, must describe the network being loaded.
//! Values of another float dtype (float16, bfloat16, float64) are converted.

use std::collections::HashMap;
use std::path::Path;

use tch::nn::VarStore;

use crate::error::Result;
use crate::io::Staged;
use crate::nn::UNetConfig;
use crate::train::pytorch::{self, TorchArchitecture};
use crate::train::tensors::ckpt_error;
pub use crate::train::tensors::{
    named_variables, read_info, stage_tensors, write_tensors, CheckpointInfo, TensorFile, FORMAT,
    FORMAT_VERSION,
};

/// Saves every variable of `vs` with `info` as metadata, atomically.
pub fn save(path: &Path, vs: &VarStore, info: &CheckpointInfo) -> Result<()> {
    stage(path, vs, info)?.commit()
}

/// [`save`] up to the rename (see [`crate::io::stage_bytes`]).
pub fn stage(path: &Path, vs: &VarStore, info: &CheckpointInfo) -> Result<Staged> {
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), FORMAT.to_string());
    meta.insert("step".to_string(), info.step.to_string());
    meta.insert("kernel".to_string(), info.kernel.clone());
    meta.insert("task".to_string(), info.model.head.task_name().to_string());
    let mut info = info.clone();
    info.metrics.retain(|_, v| v.is_finite());
    meta.insert(
        "calibconv".to_string(),
        serde_json::to_string(&info).expect("checkpoint info serialises"),
    );
    stage_tensors(path, &named_variables(vs), meta)
}

/// What [`load`] found.
#[derive(Debug)]
pub struct Loaded {
    /// The file's calibconv metadata (`None` for a foreign state dict).
    pub info: Option<CheckpointInfo>,
    /// Names in the file that were skipped ([`pytorch::dropped_on_import`]).
    pub ignored: Vec<String>,
    /// The converter's architecture record of a converted PyTorch checkpoint, if it has one
    /// (checked against the network).
    pub torch_architecture: Option<TorchArchitecture>,
}

/// Loads the checkpoint at `path` into `vs`, which holds a network of architecture `expected`.
///
/// Errors (naming the file): unreadable file; calibconv metadata for another architecture
/// (e.g. another task or width; the kernel kind, camera and input size may differ: that is how
/// standard-kernel weights become a calibrated network); a converted PyTorch checkpoint whose
/// architecture record ([`TorchArchitecture::of_file`]) differs (every difference listed); any
/// tensor missing, unexpected or of another shape (all listed, the first mismatch first).
/// Nothing is modified on error.
pub fn load(path: &Path, vs: &VarStore, expected: &UNetConfig) -> Result<Loaded> {
    load_with(path, vs, expected, |_| false)
}

/// [`load`] for the starting weights of a run: parameters that the network's kind adds to the
/// U-Net ([`crate::nn::is_added_parameter`]: the CAM-Conv map weights, learned offset branches)
/// may be absent from the file (a baseline trained without them) and then keep their
/// initialisation; present, they are loaded like every other tensor.
pub fn load_init(path: &Path, vs: &VarStore, expected: &UNetConfig) -> Result<Loaded> {
    load_with(path, vs, expected, crate::nn::is_added_parameter)
}

fn load_with(
    path: &Path,
    vs: &VarStore,
    expected: &UNetConfig,
    optional: fn(&str) -> bool,
) -> Result<Loaded> {
    let file = TensorFile::open(path)?;
    let info = file.info()?;
    let torch_architecture = match info {
        Some(_) => None,
        None => TorchArchitecture::of_file(path, &file)?,
    };
    if let Some(arch) = &torch_architecture {
        let diff = arch.differences(expected);
        if !diff.is_empty() {
            return Err(ckpt_error(
                path,
                format!(
                    "converted PyTorch checkpoint that does not fit this {}: {}",
                    describe(expected),
                    diff.join("; ")
                ),
            ));
        }
    }
    if let Some(info) = &info {
        if info.model != *expected {
            return Err(ckpt_error(
                path,
                format!(
                    "written for another architecture: {} in the file, {} in this network",
                    describe(&info.model),
                    describe(expected)
                ),
            ));
        }
    }
    let ignored = file.copy_into(&named_variables(vs), pytorch::dropped_on_import, optional)?;
    Ok(Loaded {
        info,
        ignored,
        torch_architecture,
    })
}

/// A one-line description of an architecture.
pub fn describe(cfg: &UNetConfig) -> String {
    let head = match cfg.head {
        crate::nn::Head::Depth => "depth".to_string(),
        crate::nn::Head::Segmentation { classes } => format!("segmentation ({classes} classes)"),
    };
    format!(
        "{head} U-Net (in {}, base {}, depth {}, {:?} up-sampling)",
        cfg.in_channels, cfg.base, cfg.depth, cfg.up
    )
}

#[cfg(test)]
mod tests {
    use tch::nn::VarStore;
    use tch::{Device, Kind, Tensor};

    use super::*;
    use crate::nn::{ConvKind, Head, UNet};

    fn info(cfg: UNetConfig) -> CheckpointInfo {
        CheckpointInfo {
            experiment: Some("t".into()),
            step: 12,
            epoch: 1,
            batch_in_epoch: 2,
            metrics: [("rmse".to_string(), 0.5), ("nan".to_string(), f64::NAN)]
                .into_iter()
                .collect(),
            ..CheckpointInfo::new(cfg, [32, 32], "standard")
        }
    }

    fn net(cfg: &UNetConfig) -> VarStore {
        let vs = VarStore::new(Device::Cpu);
        UNet::new(&vs.root(), cfg, &ConvKind::Standard, [32, 32]).unwrap();
        vs
    }

    #[test]
    fn round_trip_keeps_values_and_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.safetensors");
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        tch::manual_seed(1);
        let a = net(&cfg);
        save(&path, &a, &info(cfg)).unwrap();
        tch::manual_seed(2);
        let b = net(&cfg);
        let loaded = load(&path, &b, &cfg).unwrap();
        let got = loaded.info.unwrap();
        assert_eq!(got.step, 12);
        // The header alone gives the same metadata.
        assert_eq!(read_info(&path).unwrap().unwrap().step, 12);
        // Non-finite metrics are dropped (JSON cannot hold them).
        assert_eq!(got.metrics.keys().collect::<Vec<_>>(), ["rmse"]);
        for ((na, ta), (nb, tb)) in named_variables(&a).iter().zip(named_variables(&b).iter()) {
            assert_eq!(na, nb);
            assert!(ta.equal(tb), "{na}");
        }
        let meta = TensorFile::open(&path).unwrap().metadata().unwrap();
        assert_eq!(meta["format"], FORMAT);
        assert_eq!(meta["task"], "depth");
    }

    #[test]
    fn wrong_architecture_and_shapes_are_errors_that_name_the_tensors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.safetensors");
        let tiny = UNetConfig::preset("tiny", Head::Depth).unwrap();
        save(&path, &net(&tiny), &info(tiny)).unwrap();
        let seg = UNetConfig {
            head: Head::Segmentation { classes: 3 },
            ..tiny
        };
        let err = load(&path, &net(&seg), &seg).unwrap_err().to_string();
        assert!(err.contains("another architecture"), "{err}");
        assert!(err.contains("segmentation (3 classes)"), "{err}");

        // Without metadata the tensor comparison names every mismatch.
        let vars = named_variables(&net(&tiny));
        write_tensors(&path, &vars, HashMap::new()).unwrap();
        let wider = UNetConfig { base: 4, ..tiny };
        let target = net(&wider);
        let before = named_variables(&target);
        let before: Vec<Tensor> = before.iter().map(|(_, t)| t.copy()).collect();
        let err = load(&path, &target, &wider).unwrap_err().to_string();
        assert!(err.contains("with another shape"), "{err}");
        assert!(
            err.contains("`down1.maxpool_conv.1.double_conv.0.weight`: [16, 8, 3, 3] in the file, [8, 4, 3, 3] in the network"),
            "{err}"
        );
        // Nothing was modified.
        for ((_, t), b) in named_variables(&target).iter().zip(&before) {
            assert!(t.equal(b));
        }
        // Missing and unexpected names.
        let mut partial: Vec<(String, Tensor)> = vars
            .iter()
            .map(|(n, t)| (n.clone(), t.shallow_clone()))
            .collect();
        partial.retain(|(n, _)| n != "outc.conv.bias");
        partial.push((
            "extra.weight".into(),
            Tensor::zeros([2], (Kind::Float, Device::Cpu)),
        ));
        write_tensors(&path, &partial, HashMap::new()).unwrap();
        let err = load(&path, &net(&tiny), &tiny).unwrap_err().to_string();
        assert!(
            err.contains("1 missing from the file: `outc.conv.bias` [1]"),
            "{err}"
        );
        assert!(
            err.contains("1 in the file but not in the network: `extra.weight` [2]"),
            "{err}"
        );
    }

    #[test]
    fn missing_unexpected_and_misshapen_tensors_are_listed_in_one_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.safetensors");
        let tiny = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let mut vars = named_variables(&net(&tiny));
        vars.retain(|(n, _)| n != "inc.double_conv.1.running_var");
        for (n, t) in vars.iter_mut() {
            if n == "outc.conv.weight" {
                *t = Tensor::zeros([2, 8, 1, 1], (Kind::Float, Device::Cpu));
            }
        }
        vars.push((
            "up1.extra.bias".into(),
            Tensor::zeros([3], (Kind::Float, Device::Cpu)),
        ));
        // PyTorch's BatchNorm counters are dropped by the key table, not reported.
        vars.push((
            "inc.double_conv.4.num_batches_tracked".into(),
            Tensor::zeros([], (Kind::Int64, Device::Cpu)),
        ));
        write_tensors(&path, &vars, HashMap::new()).unwrap();
        let err = load(&path, &net(&tiny), &tiny).unwrap_err().to_string();
        for part in [
            "1 with another shape: `outc.conv.weight`: [2, 8, 1, 1] in the file, [1, 8, 1, 1] in \
             the network",
            "1 missing from the file: `inc.double_conv.1.running_var` [8]",
            "1 in the file but not in the network: `up1.extra.bias` [3]",
        ] {
            assert!(err.contains(part), "{part}: {err}");
        }
        assert!(!err.contains("num_batches_tracked"), "{err}");
    }

    #[test]
    fn garbage_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.safetensors");
        std::fs::write(&path, b"not a checkpoint").unwrap();
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let err = load(&path, &net(&cfg), &cfg).unwrap_err().to_string();
        assert!(err.contains("not a readable safetensors file"), "{err}");
        let err = load(&dir.path().join("none"), &net(&cfg), &cfg)
            .unwrap_err()
            .to_string();
        assert!(err.contains("none"), "{err}");
    }
}
