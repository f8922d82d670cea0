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

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, View};
use serde::{Deserialize, Serialize};
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::io::write_atomic;
use crate::nn::UNetConfig;
use crate::train::pytorch::{self, TorchArchitecture};

/// Value of the `format` metadata key of calibconv model checkpoints.
pub const FORMAT: &str = "calibconv-checkpoint";
/// Version of [`CheckpointInfo`]'s layout.
pub const FORMAT_VERSION: u32 = 1;
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

    /// Every tensor of the file as a CPU tensor of its own dtype, sorted by name.
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let st = self.parse()?;
        let mut out = Vec::new();
        for (name, view) in st.tensors() {
            let kind = kind_of(view.dtype()).ok_or_else(|| {
                ckpt_error(
                    &self.path,
                    format!("`{name}`: unsupported dtype {:?}", view.dtype()),
                )
            })?;
            let shape: Vec<i64> = view.shape().iter().map(|&s| s as i64).collect();
            out.push((name, Tensor::f_from_data_size(view.data(), &shape, kind)?));
        }
        out.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(out)
    }

    /// Copies the file's tensors into `targets` (name, variable), after checking that the names
    /// and shapes match exactly (names [`pytorch::dropped_on_import`] drops are skipped).
    /// On any mismatch nothing is copied and the error lists all of them. Returns the names
    /// that were skipped.
    pub fn copy_into(&self, targets: &[(String, Tensor)]) -> Result<Vec<String>> {
        let st = self.parse()?;
        let mut file: BTreeMap<String, _> = st.tensors().into_iter().collect();
        let ignored: Vec<String> = file
            .keys()
            .filter(|n| pytorch::dropped_on_import(n))
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
    let ignored = file.copy_into(&named_variables(vs))?;
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
