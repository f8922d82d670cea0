//! Safetensors files: named tensors written atomically with string metadata, read back
//! ([`TensorFile`]), and the metadata of calibconv checkpoints ([`CheckpointInfo`]). The file
//! layer that `checkpoint.rs` (calibconv checkpoints), `pytorch.rs` (PyTorch `state_dict`s) and
//! `adam.rs` (optimiser state) share, so that none of them imports another for it.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, View};
use serde::{Deserialize, Serialize};
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::io::{stage_with, write_failed, Staged};
use crate::nn::UNetConfig;

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

impl CheckpointInfo {
    /// The record of a network of `model` with `kernel` kernels at `input_size`, and nothing
    /// else known yet: no camera, no padding, no experiment, step 0, no metrics, no revision.
    /// Writers set what they know with struct update syntax.
    pub fn new(model: UNetConfig, input_size: [i64; 2], kernel: &str) -> Self {
        CheckpointInfo {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            model,
            input_size,
            kernel: kernel.into(),
            camera_file: None,
            camera_toml: None,
            padding: [0, 0],
            experiment: None,
            step: 0,
            epoch: 0,
            batch_in_epoch: 0,
            metrics: Default::default(),
            git: None,
        }
    }
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

pub(crate) fn ckpt_error(path: &Path, message: impl Into<String>) -> Error {
    Error::Checkpoint {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Writes named tensors and string metadata to `path` atomically (temporary file + rename); a
/// failed write (a full disk) is an [`Error::Write`] naming `path`, which stays as it was.
pub fn write_tensors(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<()> {
    stage_tensors(path, tensors, metadata)?.commit()
}

/// [`write_tensors`] up to the rename: the file is written in full next to `path` and put in
/// place by [`Staged::commit`] (see [`crate::io::stage_with`]).
pub fn stage_tensors(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<Staged> {
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
    stage_with(path, |tmp| {
        safetensors::serialize_to_file(views, &Some(metadata), tmp).map_err(|e| match e {
            safetensors::SafeTensorError::IoError(e) => write_failed(path, e),
            e => ckpt_error(path, e.to_string()),
        })
    })
}

/// The calibconv `metadata` of the checkpoint at `path`, checked against this build's format.
fn parse_info(path: &Path, metadata: Option<&String>) -> Result<Option<CheckpointInfo>> {
    let Some(json) = metadata else {
        return Ok(None);
    };
    let info: CheckpointInfo = serde_json::from_str(json)
        .map_err(|e| ckpt_error(path, format!("unreadable `calibconv` metadata: {e}")))?;
    if info.format != FORMAT || info.version != FORMAT_VERSION {
        return Err(ckpt_error(
            path,
            format!(
                "format {} version {}, this build reads {FORMAT} version {FORMAT_VERSION}",
                info.format, info.version
            ),
        ));
    }
    Ok(Some(info))
}

/// Largest safetensors header [`read_info`] reads (the format's own limit is 100 MB; a
/// checkpoint's header is a few kB).
const MAX_HEADER: u64 = 100_000_000;

/// The calibconv [`CheckpointInfo`] of the checkpoint at `path` (`None` for a file without it)
/// from the file's header alone, without reading its tensors: what a status view needs of a
/// checkpoint that may be large and on a network file system.
pub fn read_info(path: &Path) -> Result<Option<CheckpointInfo>> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut n = [0u8; 8];
    f.read_exact(&mut n).map_err(|e| Error::io(path, e))?;
    let n = u64::from_le_bytes(n);
    if n > MAX_HEADER {
        return Err(ckpt_error(
            path,
            format!("header of {n} bytes: not a checkpoint"),
        ));
    }
    let mut header = vec![0u8; n as usize];
    f.read_exact(&mut header).map_err(|e| Error::io(path, e))?;
    let header: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| ckpt_error(path, format!("not a readable safetensors header: {e}")))?;
    let meta = header
        .get("__metadata__")
        .and_then(|m| m.get("calibconv"))
        .and_then(|c| c.as_str())
        .map(String::from);
    parse_info(path, meta.as_ref())
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
        parse_info(&self.path, self.metadata()?.get("calibconv"))
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
    /// and shapes match exactly (file names for which `skip` holds are left out, e.g.
    /// [`crate::train::pytorch::dropped_on_import`]; targets for which `optional` holds may be
    /// absent from the file and then keep their values). On any mismatch nothing is copied and the error lists all of them. Returns the names
    /// that were skipped.
    pub fn copy_into(
        &self,
        targets: &[(String, Tensor)],
        skip: impl Fn(&str) -> bool,
        optional: impl Fn(&str) -> bool,
    ) -> Result<Vec<String>> {
        let st = self.parse()?;
        let mut file: BTreeMap<String, _> = st.tensors().into_iter().collect();
        let ignored: Vec<String> = file.keys().filter(|n| skip(n)).cloned().collect();
        for n in &ignored {
            file.remove(n);
        }
        let mut sorted: Vec<&(String, Tensor)> = targets.iter().collect();
        sorted.sort_by(|a, b| a.0.cmp(&b.0));
        let (mut missing, mut shape, mut dtype) = (Vec::new(), Vec::new(), Vec::new());
        for (name, var) in &sorted {
            match file.get(name) {
                None if optional(name) => {}
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
                // (An optional target the file lacks keeps its value.)
                let Some(view) = file.get(name) else {
                    continue;
                };
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
