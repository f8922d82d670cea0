//! PyTorch state dicts of milesial/Pytorch-UNet: the one table that relates their keys to
//! calibconv's variables ([`KEY_RULES`]), the architecture record the converter
//! (`tools/convert_checkpoint.py`) writes and that loading checks ([`TorchArchitecture`]), and
//! export back to a `state_dict` that `UNet.load_state_dict(strict=True)` accepts ([`export`]).
//!
//! # The key mapping
//!
//! [`crate::nn::UNet`] names its variables as milesial's modules do (`inc.double_conv.0.weight`,
//! `down1.maxpool_conv.1.double_conv.4.running_var`, `up1.up.weight`, `outc.conv.bias`), with
//! the same layouts (conv weights `[C_out, C_in, kH, kW]`, transposed-conv weights
//! `[C_in, C_out, kH, kW]`, both in PyTorch and tch), so every parameter and running statistic
//! maps to itself. The only difference is BatchNorm's `num_batches_tracked`: an int64 counter
//! PyTorch keeps for `momentum = None` (a cumulative average) and tch does not have. With
//! milesial's fixed `momentum = 0.1` it never affects an output, so it is **dropped on import**
//! and **written as a 0-d int64 zero on export** next to every `running_var` (as a freshly
//! built PyTorch model has it), which is what `load_state_dict(strict=True)` needs. Nothing else
//! is renamed: a key without a rule is an unexpected key.

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

use super::tensors::{self, TensorFile};
use crate::error::{Error, Result};
use crate::nn::{Head, UNetConfig, UpMode};

/// How a PyTorch `state_dict` key relates to a calibconv variable.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeyMapping {
    /// The same name, shape, layout and values in both.
    Same,
    /// A PyTorch-only BatchNorm counter: dropped on import; on export, one 0-d int64 zero
    /// `P.num_batches_tracked` is written for every variable `P.running_var`.
    BatchNormCounter,
}

/// One row of [`KEY_RULES`]: keys ending in `suffix` map by `mapping`.
#[derive(Clone, Copy, Debug)]
pub struct KeyRule {
    pub suffix: &'static str,
    pub mapping: KeyMapping,
    /// Which tensors these are.
    pub what: &'static str,
}

/// Suffix of the BatchNorm variable next to which export writes the counter.
const COUNTER_COMPANION: &str = ".running_var";

/// The whole mapping between milesial/Pytorch-UNet `state_dict` keys and calibconv variables.
pub const KEY_RULES: [KeyRule; 5] = [
    KeyRule {
        suffix: ".weight",
        mapping: KeyMapping::Same,
        what: "conv [out, in, kh, kw], transposed conv [in, out, kh, kw], BatchNorm scale",
    },
    KeyRule {
        suffix: ".bias",
        mapping: KeyMapping::Same,
        what: "transposed-conv, outc and BatchNorm bias",
    },
    KeyRule {
        suffix: ".running_mean",
        mapping: KeyMapping::Same,
        what: "BatchNorm running mean",
    },
    KeyRule {
        suffix: COUNTER_COMPANION,
        mapping: KeyMapping::Same,
        what: "BatchNorm running variance",
    },
    KeyRule {
        suffix: ".num_batches_tracked",
        mapping: KeyMapping::BatchNormCounter,
        what: "BatchNorm batch counter (int64, PyTorch only)",
    },
];

/// The rule for `key`, if any.
pub fn rule_for(key: &str) -> Option<&'static KeyRule> {
    KEY_RULES.iter().find(|r| key.ends_with(r.suffix))
}

/// Whether import skips the file's `key` (it has no calibconv variable by design).
pub fn dropped_on_import(key: &str) -> bool {
    rule_for(key).is_some_and(|r| r.mapping == KeyMapping::BatchNormCounter)
}

fn counter_suffix() -> &'static str {
    KEY_RULES
        .iter()
        .find(|r| r.mapping == KeyMapping::BatchNormCounter)
        .expect("the table has a counter rule")
        .suffix
}

/// The PyTorch `state_dict` of calibconv variables `vars` (sorted by name), by [`KEY_RULES`].
/// Fails, naming them all, on variables no rule covers.
pub fn to_state_dict(vars: &[(String, Tensor)]) -> Result<Vec<(String, Tensor)>> {
    let mut out = Vec::with_capacity(vars.len() * 5 / 4);
    let mut unmapped = Vec::new();
    for (name, t) in vars {
        match rule_for(name).map(|r| r.mapping) {
            Some(KeyMapping::Same) => {
                out.push((name.clone(), t.shallow_clone()));
                if let Some(prefix) = name.strip_suffix(COUNTER_COMPANION) {
                    out.push((
                        format!("{prefix}{}", counter_suffix()),
                        Tensor::zeros([], (Kind::Int64, Device::Cpu)),
                    ));
                }
            }
            Some(KeyMapping::BatchNormCounter) | None => unmapped.push(format!("`{name}`")),
        }
    }
    if !unmapped.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "{} variables have no PyTorch name: {}",
            unmapped.len(),
            unmapped.join(", ")
        )));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// The architecture the converter detects from milesial/Pytorch-UNet keys (the `architecture`
/// entry of its JSON sidecar and safetensors metadata), and that export records.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TorchArchitecture {
    /// `milesial-unet`.
    pub name: String,
    /// `transposed` or `bilinear`.
    pub variant: String,
    pub in_channels: i64,
    /// Output channels of `outc` (1 for a calibconv depth network).
    pub classes: i64,
    /// Width of `inc` (64 in the public network).
    pub base: i64,
    /// Number of `down` blocks (4 in the public network).
    pub depth: usize,
}

/// [`TorchArchitecture::name`] of milesial/Pytorch-UNet.
pub const MILESIAL: &str = "milesial-unet";

impl TorchArchitecture {
    /// The record of a calibconv architecture.
    pub fn of(cfg: &UNetConfig) -> Self {
        TorchArchitecture {
            name: MILESIAL.into(),
            variant: variant_name(cfg.up).into(),
            in_channels: cfg.in_channels,
            classes: cfg.head.channels(),
            base: cfg.base,
            depth: cfg.depth,
        }
    }

    /// Every difference from the network `cfg` (empty if it fits), e.g.
    /// `classes: 2 in the file, 1 in the network (depth)`.
    pub fn differences(&self, cfg: &UNetConfig) -> Vec<String> {
        let want = TorchArchitecture::of(cfg);
        let mut d = Vec::new();
        if self.name != want.name {
            d.push(format!(
                "architecture `{}`, expected `{}`",
                self.name, want.name
            ));
        }
        let mut cmp = |field: &str, file: String, net: String, note: &str| {
            if file != net {
                d.push(format!(
                    "{field}: {file} in the file, {net} in the network{note}"
                ));
            }
        };
        cmp("up-sampling", self.variant.clone(), want.variant, "");
        cmp(
            "in_channels",
            self.in_channels.to_string(),
            want.in_channels.to_string(),
            "",
        );
        let head_note = match cfg.head {
            Head::Depth => " (a depth network has 1)",
            Head::Segmentation { .. } => " (segmentation classes)",
        };
        cmp(
            "classes",
            self.classes.to_string(),
            want.classes.to_string(),
            head_note,
        );
        cmp("base", self.base.to_string(), want.base.to_string(), "");
        cmp("depth", self.depth.to_string(), want.depth.to_string(), "");
        d
    }

    /// Reads the record of a converted file: the `architecture` metadata entry of the
    /// safetensors file (JSON, or `unknown`), else the `architecture` of the JSON sidecar next
    /// to it (`W.json` for `W.safetensors`). `None` when neither says anything.
    pub fn of_file(path: &Path, file: &TensorFile) -> Result<Option<Self>> {
        let bad = |e: String| Error::Checkpoint {
            path: path.to_path_buf(),
            message: format!("unreadable `architecture` record: {e}"),
        };
        if let Some(text) = file.metadata()?.get("architecture") {
            if text == "unknown" {
                return Ok(None);
            }
            return serde_json::from_str(text)
                .map(Some)
                .map_err(|e| bad(e.to_string()));
        }
        let sidecar = path.with_extension("json");
        let Ok(text) = std::fs::read_to_string(&sidecar) else {
            return Ok(None);
        };
        let doc: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| bad(format!("{}: {e}", sidecar.display())))?;
        match doc.get("architecture") {
            None | Some(serde_json::Value::Null) => Ok(None),
            Some(v) => serde_json::from_value(v.clone())
                .map(Some)
                .map_err(|e| bad(format!("{}: {e}", sidecar.display()))),
        }
    }
}

fn variant_name(up: UpMode) -> &'static str {
    match up {
        UpMode::Transposed => "transposed",
        UpMode::Bilinear => "bilinear",
    }
}

/// What [`export`] wrote.
#[derive(Debug)]
pub struct Exported {
    pub architecture: TorchArchitecture,
    /// Keys written (parameters, running statistics, counters).
    pub keys: usize,
    /// The checkpoint's kernel kind (`calibrated` weights give other outputs in a standard
    /// PyTorch network).
    pub kernel: String,
}

/// Writes the calibconv checkpoint `checkpoint` as a PyTorch `state_dict` in safetensors at
/// `out` (atomically): milesial names by [`KEY_RULES`], `num_batches_tracked` included, float32
/// as trained, metadata `format = pt`, `architecture` (JSON [`TorchArchitecture`]) and `source`.
/// `safetensors.torch.load_file(out)` then loads with `strict=True` into milesial's
/// `UNet(in_channels, classes, bilinear)` (for `base = 64`, `depth = 4`; other sizes into the
/// same blocks with those widths, e.g. `tools/reference_unet.py`).
///
/// Fails on a file without calibconv metadata (nothing to say which architecture it is).
pub fn export(checkpoint: &Path, out: &Path) -> Result<Exported> {
    let file = TensorFile::open(checkpoint)?;
    let info = file.info()?.ok_or_else(|| Error::Checkpoint {
        path: checkpoint.to_path_buf(),
        message: "not a calibconv checkpoint (no `calibconv` metadata); a PyTorch state dict \
                  needs no export"
            .into(),
    })?;
    let vars = file.tensors()?;
    let state = to_state_dict(&vars).map_err(|e| Error::Checkpoint {
        path: checkpoint.to_path_buf(),
        message: e.to_string(),
    })?;
    let architecture = TorchArchitecture::of(&info.model);
    let meta: HashMap<String, String> = [
        ("format", "pt".to_string()),
        (
            "architecture",
            serde_json::to_string(&architecture).expect("serialises"),
        ),
        ("source", checkpoint.display().to_string()),
        ("source_step", info.step.to_string()),
        ("source_kernel", info.kernel.clone()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    tensors::write_tensors(out, &state, meta)?;
    Ok(Exported {
        architecture,
        keys: state.len(),
        kernel: info.kernel,
    })
}

#[cfg(test)]
mod tests {
    use tch::nn::VarStore;

    use super::*;
    use crate::nn::{ConvKind, UNet};

    #[test]
    fn every_unet_variable_has_a_rule_and_counters_follow_running_vars() {
        for preset in ["classic", "classic-bilinear"] {
            let cfg = UNetConfig::preset(preset, Head::Segmentation { classes: 2 }).unwrap();
            let vs = VarStore::new(Device::Cpu);
            UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [64, 64]).unwrap();
            let state = to_state_dict(&tensors::named_variables(&vs)).unwrap();
            // milesial/Pytorch-UNet UNet(3, 2): 118 keys (transposed), 110 (bilinear).
            let want = if preset == "classic" { 118 } else { 110 };
            assert_eq!(state.len(), want, "{preset}");
            let counters: Vec<_> = state.iter().filter(|(n, _)| dropped_on_import(n)).collect();
            assert_eq!(counters.len(), 18, "{preset}");
            for (_, t) in counters {
                assert_eq!((t.size(), t.kind()), (vec![], Kind::Int64));
            }
        }
        let err = to_state_dict(&[(
            "inc.double_conv.1.momentum".into(),
            Tensor::zeros([1], (Kind::Float, Device::Cpu)),
        )])
        .unwrap_err();
        assert!(
            err.to_string().contains("inc.double_conv.1.momentum"),
            "{err}"
        );
    }

    #[test]
    fn architecture_differences_are_listed_together() {
        let cfg = UNetConfig::preset("small", Head::Depth).unwrap();
        assert!(TorchArchitecture::of(&cfg).differences(&cfg).is_empty());
        let file = TorchArchitecture {
            variant: "bilinear".into(),
            classes: 2,
            base: 64,
            ..TorchArchitecture::of(&cfg)
        };
        let d = file.differences(&cfg);
        assert_eq!(d.len(), 3, "{d:?}");
        assert_eq!(
            d[0],
            "up-sampling: bilinear in the file, transposed in the network"
        );
        assert_eq!(
            d[1],
            "classes: 2 in the file, 1 in the network (a depth network has 1)"
        );
        assert_eq!(d[2], "base: 64 in the file, 16 in the network");
    }
}
