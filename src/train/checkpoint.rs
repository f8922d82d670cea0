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
//! with `safetensors.torch.save_file`, or by `tools/convert_checkpoint.py` from a `.pth`, e.g.
//! milesial/Pytorch-UNet weights): their BatchNorm `num_batches_tracked` entries are ignored (tch
//! has no such buffer), every other name must match, and the converter's `architecture`
//! metadata, when present, must describe the network. Values of another float dtype (float16,
//! bfloat16, float64) are converted.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, View};
use serde::{Deserialize, Serialize};
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::io::write_atomic;
use crate::nn::{UNetConfig, UpMode};

/// Value of the `format` metadata key of calibconv model checkpoints.
pub const FORMAT: &str = "calibconv-checkpoint";
/// Version of [`CheckpointInfo`]'s layout.
pub const FORMAT_VERSION: u32 = 1;
/// Names ending with this are PyTorch BatchNorm buffers tch does not have; loading skips them.
pub const IGNORED_SUFFIX: &str = ".num_batches_tracked";
/// How many mismatching names an error lists per category before "and N more".
const MAX_LISTED: usize = 8;

/// What a calibconv checkpoint says about itself (the `calibconv` metadata key, JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckpointInfo {
    /// [`FORMAT`].
    pub format: String,
    /// [`FORMAT_VERSION`].
    pub version: u32,
    /// The architecture.
    pub model: UNetConfig,
    /// Network input `[H, W]` the weights were trained at.
    pub input_size: [i64; 2],
    /// `standard` or `calibrated`.
    pub kernel: String,
    /// The camera file the network was built for, and its text.
    pub camera_file: Option<PathBuf>,
    pub camera_toml: Option<String>,
    /// Input padding `[p_w, p_h]` of the camera image, camera pixels.
    pub padding: [usize; 2],
    /// The experiment that wrote it.
    pub experiment: Option<String>,
    /// Optimiser steps done.
    pub step: u64,
    /// Where the data order continues: epoch, and batches of it already used.
    pub epoch: u64,
    pub batch_in_epoch: u64,
    /// Metrics at this step (validation metrics, the last training loss), finite values only.
    pub metrics: BTreeMap<String, f64>,
    /// `git describe`-like revision of the code that wrote it, if known.
    pub git: Option<String>,
}

/// An owned tensor buffer for the `safetensors` writer.
struct Buffer {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl View for &Buffer {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

fn dtype_of(kind: Kind) -> Option<Dtype> {
    Some(match kind {
        Kind::Float => Dtype::F32,
        Kind::Double => Dtype::F64,
        Kind::Half => Dtype::F16,
        Kind::BFloat16 => Dtype::BF16,
        Kind::Int64 => Dtype::I64,
        Kind::Int => Dtype::I32,
        Kind::Uint8 => Dtype::U8,
        Kind::Bool => Dtype::BOOL,
        _ => return None,
    })
}

fn kind_of(dtype: Dtype) -> Option<Kind> {
    Some(match dtype {
        Dtype::F32 => Kind::Float,
        Dtype::F64 => Kind::Double,
        Dtype::F16 => Kind::Half,
        Dtype::BF16 => Kind::BFloat16,
        Dtype::I64 => Kind::Int64,
        Dtype::I32 => Kind::Int,
        Dtype::U8 => Kind::Uint8,
        Dtype::BOOL => Kind::Bool,
        _ => return None,
    })
}

fn ckpt_error(path: &Path, message: impl Into<String>) -> Error {
    Error::Checkpoint {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Writes named tensors and string metadata to `path` atomically (temporary file + rename).
pub fn write_tensors(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<()> {
    let mut buffers = Vec::with_capacity(tensors.len());
    for (name, t) in tensors {
        let t = t.detach().to_device(Device::Cpu).contiguous();
        let dtype = dtype_of(t.kind()).ok_or_else(|| {
            ckpt_error(
                path,
                format!("tensor `{name}` has unsupported kind {:?}", t.kind()),
            )
        })?;
        let numel = t.numel();
        let mut data = vec![0u8; numel * t.kind().elt_size_in_bytes()];
        t.f_copy_data_u8(&mut data, numel)?;
        let shape = t.size().iter().map(|&s| s as usize).collect();
        buffers.push((name.clone(), Buffer { dtype, shape, data }));
    }
    let views: Vec<(&str, &Buffer)> = buffers.iter().map(|(n, b)| (n.as_str(), b)).collect();
    write_atomic(path, |tmp| {
        safetensors::serialize_to_file(views, &Some(metadata), tmp)
            .map_err(|e| ckpt_error(path, e.to_string()))
    })
}

/// A safetensors file read into memory.
pub struct TensorFile {
    path: PathBuf,
    bytes: Vec<u8>,
}

impl TensorFile {
    /// Reads `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let file = TensorFile {
            path: path.to_path_buf(),
            bytes,
        };
        file.parse()?;
        Ok(file)
    }

    fn parse(&self) -> Result<SafeTensors<'_>> {
        SafeTensors::deserialize(&self.bytes)
            .map_err(|e| ckpt_error(&self.path, format!("not a readable safetensors file: {e}")))
    }

    /// The string metadata (empty if none).
    pub fn metadata(&self) -> Result<HashMap<String, String>> {
        let (_, meta) = SafeTensors::read_metadata(&self.bytes)
            .map_err(|e| ckpt_error(&self.path, e.to_string()))?;
        Ok(meta.metadata().clone().unwrap_or_default())
    }

    /// The calibconv [`CheckpointInfo`], or `None` for a file without it (a foreign state dict).
    pub fn info(&self) -> Result<Option<CheckpointInfo>> {
        match self.metadata()?.get("calibconv") {
            None => Ok(None),
            Some(json) => {
                let info: CheckpointInfo = serde_json::from_str(json).map_err(|e| {
                    ckpt_error(&self.path, format!("unreadable `calibconv` metadata: {e}"))
                })?;
                if info.format != FORMAT || info.version != FORMAT_VERSION {
                    return Err(ckpt_error(
                        &self.path,
                        format!(
                            "format {} version {}, this build reads {FORMAT} version \
                             {FORMAT_VERSION}",
                            info.format, info.version
                        ),
                    ));
                }
                Ok(Some(info))
            }
        }
    }

    /// Names and shapes of the tensors in the file, sorted by name.
    pub fn shapes(&self) -> Result<BTreeMap<String, Vec<i64>>> {
        Ok(self
            .parse()?
            .tensors()
            .into_iter()
            .map(|(n, v)| (n, v.shape().iter().map(|&s| s as i64).collect()))
            .collect())
    }

    /// Copies the file's tensors into `targets` (name, variable), after checking that the names
    /// and shapes match exactly (names ending in [`IGNORED_SUFFIX`] in the file are skipped).
    /// On any mismatch nothing is copied and the error lists all of them. Returns the names
    /// that were skipped.
    pub fn copy_into(&self, targets: &[(String, Tensor)]) -> Result<Vec<String>> {
        let st = self.parse()?;
        let mut file: BTreeMap<String, _> = st.tensors().into_iter().collect();
        let ignored: Vec<String> = file
            .keys()
            .filter(|n| n.ends_with(IGNORED_SUFFIX))
            .cloned()
            .collect();
        for n in &ignored {
            file.remove(n);
        }
        let mut sorted: Vec<&(String, Tensor)> = targets.iter().collect();
        sorted.sort_by(|a, b| a.0.cmp(&b.0));
        let (mut missing, mut shape, mut dtype) = (Vec::new(), Vec::new(), Vec::new());
        for (name, var) in &sorted {
            match file.get(name) {
                None => missing.push(format!("`{name}` {:?}", var.size())),
                Some(view) => {
                    let s: Vec<i64> = view.shape().iter().map(|&x| x as i64).collect();
                    if s != var.size() {
                        shape.push(format!(
                            "`{name}`: {s:?} in the file, {:?} in the network",
                            var.size()
                        ));
                    } else if kind_of(view.dtype()).is_none() {
                        dtype.push(format!("`{name}`: unsupported dtype {:?}", view.dtype()));
                    }
                }
            }
        }
        let wanted: std::collections::HashSet<&str> =
            targets.iter().map(|(n, _)| n.as_str()).collect();
        let unexpected: Vec<String> = file
            .iter()
            .filter(|(n, _)| !wanted.contains(n.as_str()))
            .map(|(n, v)| format!("`{n}` {:?}", v.shape()))
            .collect();
        if !(missing.is_empty() && shape.is_empty() && dtype.is_empty() && unexpected.is_empty()) {
            let mut parts = Vec::new();
            let mut list = |what: &str, items: &[String]| {
                if items.is_empty() {
                    return;
                }
                let shown = items
                    .iter()
                    .take(MAX_LISTED)
                    .cloned()
                    .collect::<Vec<_>>()
                    .join(", ");
                let more = items.len().saturating_sub(MAX_LISTED);
                let more = if more > 0 {
                    format!(" and {more} more")
                } else {
                    String::new()
                };
                parts.push(format!("{} {what}: {shown}{more}", items.len()));
            };
            list("with another shape", &shape);
            list("missing from the file", &missing);
            list("in the file but not in the network", &unexpected);
            list("with an unsupported dtype", &dtype);
            return Err(ckpt_error(
                &self.path,
                format!("does not fit this network: {}", parts.join("; ")),
            ));
        }
        tch::no_grad(|| -> Result<()> {
            for (name, var) in targets {
                let view = &file[name];
                let kind = kind_of(view.dtype()).expect("checked above");
                let t = Tensor::f_from_data_size(view.data(), &var.size(), kind)?
                    .to_kind(var.kind())
                    .to_device(var.device());
                let mut var = var.shallow_clone();
                var.f_copy_(&t)?;
            }
            Ok(())
        })?;
        Ok(ignored)
    }
}

/// The variables of `vs` by name, sorted.
pub fn named_variables(vs: &VarStore) -> Vec<(String, Tensor)> {
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

/// Saves every variable of `vs` with `info` as metadata, atomically.
pub fn save(path: &Path, vs: &VarStore, info: &CheckpointInfo) -> Result<()> {
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
    write_tensors(path, &named_variables(vs), meta)
}

/// What [`load`] found.
#[derive(Debug)]
pub struct Loaded {
    /// The file's calibconv metadata (`None` for a foreign state dict).
    pub info: Option<CheckpointInfo>,
    /// Names in the file that were skipped ([`IGNORED_SUFFIX`]).
    pub ignored: Vec<String>,
}

/// Loads the checkpoint at `path` into `vs`, which holds a network of architecture `expected`.
///
/// Errors (naming the file): unreadable file; calibconv metadata for another architecture
/// (e.g. another task or width; the kernel kind, camera and input size may differ: that is how
/// standard-kernel weights become a calibrated network); any tensor missing, unexpected or of
/// another shape (all listed, the first mismatch first). Nothing is modified on error.
pub fn load(path: &Path, vs: &VarStore, expected: &UNetConfig) -> Result<Loaded> {
    let file = TensorFile::open(path)?;
    let info = file.info()?;
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
    if info.is_none() {
        check_converted_architecture(path, &file.metadata()?, expected)?;
    }
    let ignored = file.copy_into(&named_variables(vs))?;
    Ok(Loaded { info, ignored })
}

/// Checks the `architecture` metadata that `tools/convert_checkpoint.py` writes for a PyTorch
/// milesial U-Net (`{"name": "milesial-unet", "variant": "transposed" | "bilinear",
/// "in_channels", "classes", "base", "depth"}`) against `expected`; files without it pass.
fn check_converted_architecture(
    path: &Path,
    meta: &HashMap<String, String>,
    expected: &UNetConfig,
) -> Result<()> {
    let Some(arch) = meta
        .get("architecture")
        .and_then(|a| serde_json::from_str::<serde_json::Value>(a).ok())
    else {
        return Ok(());
    };
    if arch["name"] != "milesial-unet" {
        return Ok(());
    }
    let up = match arch["variant"].as_str() {
        Some("bilinear") => UpMode::Bilinear,
        _ => UpMode::Transposed,
    };
    let int = |k: &str| arch[k].as_i64();
    let fits = int("in_channels") == Some(expected.in_channels)
        && int("base") == Some(expected.base)
        && int("depth") == Some(expected.depth as i64)
        && int("classes") == Some(expected.head.channels())
        && up == expected.up;
    if fits {
        Ok(())
    } else {
        Err(ckpt_error(
            path,
            format!(
                "converted from a milesial U-Net ({} up-sampling, in {}, {} output channels, base \
                 {}, depth {}); this network is a {} with {} output channels",
                arch["variant"].as_str().unwrap_or("?"),
                arch["in_channels"],
                arch["classes"],
                arch["base"],
                arch["depth"],
                describe(expected),
                expected.head.channels()
            ),
        ))
    }
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

    use super::*;
    use crate::nn::{ConvKind, Head, UNet};

    fn info(cfg: UNetConfig) -> CheckpointInfo {
        CheckpointInfo {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            model: cfg,
            input_size: [32, 32],
            kernel: "standard".into(),
            camera_file: None,
            camera_toml: None,
            padding: [0, 0],
            experiment: Some("t".into()),
            step: 12,
            epoch: 1,
            batch_in_epoch: 2,
            metrics: [("rmse".to_string(), 0.5), ("nan".to_string(), f64::NAN)]
                .into_iter()
                .collect(),
            git: None,
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
    fn the_converters_architecture_metadata_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.safetensors");
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let vars = named_variables(&net(&cfg));
        let arch = |classes: i64| {
            let a = format!(
                r#"{{"name": "milesial-unet", "variant": "transposed", "in_channels": 3, "classes": {classes}, "base": 8, "depth": 3}}"#
            );
            [("architecture".to_string(), a)].into_iter().collect()
        };
        write_tensors(&path, &vars, arch(1)).unwrap();
        load(&path, &net(&cfg), &cfg).unwrap();
        write_tensors(&path, &vars, arch(2)).unwrap();
        let err = load(&path, &net(&cfg), &cfg).unwrap_err().to_string();
        assert!(
            err.contains("converted from a milesial U-Net") && err.contains("2 output channels"),
            "{err}"
        );
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
