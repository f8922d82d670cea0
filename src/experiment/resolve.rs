//! Validation: [`RawExperiment::resolve`] turns the file as written into an [`Experiment`],
//! section by section in the file's order (name and device, model, init, input, data, train,
//! optimiser and schedule, output, evaluations), so the first bad value is the one reported.
//! Every error is an [`Error::Config`] naming the file and the dotted key.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::{
    layout, parse_device, suggest, EvalSpec, Experiment, InitSpec, InputSpec, KernelName, LossName,
    OptimizerName, RawAugment, RawEval, RawExperiment, RawInit, RawModel, RawOptimizer,
    RawSchedule, RawSource, RawTrain, ScheduleName, SourceSpec, Task, TrainSpec, DEFAULT_OUTPUT,
};
use crate::camera::{self, CameraModel, PixelConvention};
use crate::data::loader::{Augment, ColorJitter};
use crate::data::NUM_CLASSES;
use crate::error::{Error, Result};
use crate::eval::metrics::{Metric, DEPTH_METRICS, SEGMENTATION_METRICS};
use crate::kernel::{kernel_focal, pyramid_sizes};
use crate::loss::DepthLoss;
use crate::nn::unet::PRESETS as PRESETS_LIST;
use crate::nn::{Head, UNetConfig};
use crate::train::adam::AdamConfig;
use crate::train::schedule::{Decay, Schedule};
use crate::train::Length;

/// The error for `field` of the experiment file `cfg`.
fn bad(cfg: &Path, field: &str, message: String) -> Error {
    Error::Config {
        path: cfg.to_path_buf(),
        field: field.to_string(),
        message,
    }
}

/// `x > 0` (false for NaN).
fn positive(x: f64) -> bool {
    x > 0.0
}

fn absolute(p: &Path) -> Result<PathBuf> {
    std::path::absolute(p).map_err(|e| Error::io(p, e))
}

/// An enum's name as the file spells it (`cross-entropy`).
fn spelt<T: serde::Serialize>(value: T) -> String {
    serde_json::to_value(value)
        .expect("enum")
        .as_str()
        .unwrap_or("")
        .to_string()
}

impl RawSource {
    fn resolve(self, cfg: &Path, field: &str, root: &Path) -> Result<SourceSpec> {
        let bad = |message: &str| bad(cfg, field, message.to_string());
        if self.split.is_empty() {
            return Err(bad("`split` must not be empty"));
        }
        if let Some(f) = self.fraction {
            if field != "data.train" {
                return Err(bad("`fraction` applies to `data.train` only"));
            }
            if !(f > 0.0 && f <= 1.0) {
                return Err(bad(&format!("`fraction` must lie in (0, 1], got {f}")));
            }
            if self.dataset.is_none() {
                return Err(bad(
                    "`fraction` needs a `dataset` (the toy task has a size instead)",
                ));
            }
        }
        match (self.dataset, self.toy) {
            (Some(p), None) => Ok(SourceSpec::Dataset {
                path: absolute(&root.join(p))?,
                split: self.split,
                fraction: self.fraction,
            }),
            (None, Some(0)) => Err(bad("`toy` needs at least one sample")),
            (None, Some(n)) => Ok(SourceSpec::Toy {
                samples: n,
                split: self.split,
            }),
            _ => Err(bad(
                "give exactly one of `dataset = \"FOLDER\"` and `toy = SAMPLES`",
            )),
        }
    }
}

/// Loads a camera and builds the input spec; `field` names the camera key in errors.
fn input_spec(
    cfg: &Path,
    field: &str,
    camera_path: &Path,
    width: Option<usize>,
    padding: Option<[usize; 2]>,
    size: Option<[i64; 2]>,
    convention: Option<PixelConvention>,
) -> Result<InputSpec> {
    let camera_file = absolute(camera_path)?;
    let camera_toml = std::fs::read_to_string(&camera_file)
        .map_err(|e| bad(cfg, field, format!("{}: {e}", camera_file.display())))?;
    let mut camera = camera::load(&camera_file).map_err(|e| bad(cfg, field, e.to_string()))?;
    let mut camera_toml = camera_toml;
    if let Some(w) = width {
        if w == 0 {
            return Err(bad(cfg, "input.width", "must be positive".into()));
        }
        let s = w as f64 / camera.size()[0] as f64;
        camera = camera.rescaled([s, s], PixelConvention::HalfPixel);
        let note = format!(
            "{} rescaled to {}x{} (half-pixel convention) by input.width",
            camera_file.display(),
            camera.size()[0],
            camera.size()[1]
        );
        camera_toml = camera::to_toml(&camera, &[], None, Some(&note));
    }
    let padding = padding.unwrap_or([0, 0]);
    let [w, h] = camera.size();
    let size = size.unwrap_or([(h + padding[1]) as i64, (w + padding[0]) as i64]);
    if size.iter().any(|&s| s < 1) {
        return Err(bad(
            cfg,
            &field.replace("camera", "size"),
            format!("must be positive, got {size:?}"),
        ));
    }
    Ok(InputSpec {
        camera_file,
        camera_toml,
        camera: Arc::new(camera),
        padding,
        convention: convention.unwrap_or_default(),
        size,
    })
}

/// Checks that calibrated 3x3 kernels fit every level of `model` on `input` (the deepest level
/// is the narrowest), so a bad combination fails at resolve time rather than at build time.
fn check_calibrated(cfg: &Path, field: &str, model: &UNetConfig, input: &InputSpec) -> Result<()> {
    let sizes = pyramid_sizes(
        [input.size[0] as usize, input.size[1] as usize],
        model.depth,
    );
    let deepest = sizes[model.depth];
    if deepest[0] == 0 || deepest[1] == 0 {
        return Err(bad(
            cfg,
            field,
            format!(
                "a {}x{} input is too small for a U-Net of depth {}",
                input.size[0], input.size[1], model.depth
            ),
        ));
    }
    kernel_focal(3, input.camera.fov(), deepest[1])
        .map(|_| ())
        .map_err(|e| {
            bad(
                cfg,
                field,
                format!(
                    "calibrated kernels at the deepest level ({}x{}): {e}",
                    deepest[0], deepest[1]
                ),
            )
        })
}

fn check_name(cfg: &Path, field: &str, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        && !name.starts_with('.');
    if ok {
        Ok(())
    } else {
        Err(bad(
            cfg,
            field,
            format!("`{name}`: use letters, digits, `-`, `_` and `.` (it names a folder)"),
        ))
    }
}

/// `[model]` without `init`: the preset for the task's head, with its overrides.
fn resolve_model(cfg: &Path, task: Task, m: &RawModel) -> Result<UNetConfig> {
    let head = match task {
        Task::Depth => {
            if m.classes.is_some() {
                return Err(bad(
                    cfg,
                    "model.classes",
                    "only for task = \"segmentation\"".into(),
                ));
            }
            Head::Depth
        }
        Task::Segmentation => {
            let classes = m.classes.unwrap_or(NUM_CLASSES as i64);
            if classes < 2 {
                return Err(bad(
                    cfg,
                    "model.classes",
                    format!("need >= 2, got {classes}"),
                ));
            }
            Head::Segmentation { classes }
        }
    };
    let mut model = UNetConfig::preset(&m.preset, head).map_err(|_| {
        let hint = suggest::did_you_mean(&m.preset, &PRESETS_LIST);
        bad(
            cfg,
            "model.preset",
            format!(
                "unknown preset `{}` (expected one of {}){hint}",
                m.preset,
                PRESETS_LIST.join(", ")
            ),
        )
    })?;
    if let Some(b) = m.base {
        model.base = b;
    }
    if let Some(d) = m.depth {
        model.depth = d;
    }
    if let Some(u) = m.up {
        model.up = u;
    }
    model
        .check()
        .map_err(|e| bad(cfg, "model", e.to_string()))?;
    Ok(model)
}

/// `model.init` of the experiment `own`: `(experiment name, None)` or `("", Some(checkpoint))`.
fn resolve_init(
    cfg: &Path,
    own: &str,
    init: Option<RawInit>,
) -> Result<Option<(String, Option<PathBuf>)>> {
    match init {
        None => Ok(None),
        Some(RawInit {
            experiment: Some(name),
            checkpoint: None,
        }) => {
            check_name(cfg, "model.init.experiment", &name)?;
            if name == own {
                return Err(bad(
                    cfg,
                    "model.init.experiment",
                    "an experiment cannot start from its own checkpoints (use --resume)".into(),
                ));
            }
            Ok(Some((name, None)))
        }
        Some(RawInit {
            experiment: None,
            checkpoint: Some(p),
        }) => Ok(Some((String::new(), Some(absolute(&p)?)))),
        Some(_) => Err(bad(
            cfg,
            "model.init",
            "give exactly one of `experiment = \"NAME\"` and `checkpoint = \"FILE\"`".into(),
        )),
    }
}

/// `train.loss` for the task (segmentation keeps the unused depth loss at L1).
fn resolve_loss(cfg: &Path, task: Task, loss: Option<LossName>) -> Result<DepthLoss> {
    match (task, loss) {
        (Task::Depth, None | Some(LossName::L1)) => Ok(DepthLoss::L1),
        (Task::Depth, Some(LossName::Berhu)) => Ok(DepthLoss::BerHu),
        (Task::Segmentation, None | Some(LossName::CrossEntropy)) => Ok(DepthLoss::L1),
        (task, Some(l)) => Err(bad(
            cfg,
            "train.loss",
            format!(
                "`{}` is not a {} loss (depth: l1, berhu; segmentation: cross-entropy)",
                spelt(l),
                spelt(task)
            ),
        )),
    }
}

/// `train.val_metric`: the loss or one of the task's metrics (default RMSE / mIoU).
fn resolve_val_metric(cfg: &Path, task: Task, val_metric: Option<&str>) -> Result<Metric> {
    let task_metrics: Vec<Metric> = match task {
        Task::Depth => DEPTH_METRICS.to_vec(),
        Task::Segmentation => SEGMENTATION_METRICS.to_vec(),
    };
    let Some(s) = val_metric else {
        return Ok(match task {
            Task::Depth => Metric::Rmse,
            Task::Segmentation => Metric::MIoU,
        });
    };
    let m = s
        .parse::<Metric>()
        .ok()
        .filter(|m| *m == Metric::Loss || task_metrics.contains(m));
    m.ok_or_else(|| {
        let mut names = vec!["loss"];
        names.extend(task_metrics.iter().map(|m| m.name()));
        let hint = suggest::did_you_mean(s, &names);
        bad(
            cfg,
            "train.val_metric",
            format!("`{s}` is not one of {}{hint}", names.join(", ")),
        )
    })
}

/// `train.augment` (none if absent).
fn resolve_augment(cfg: &Path, augment: Option<&RawAugment>) -> Result<Augment> {
    let Some(a) = augment else {
        return Ok(Augment::default());
    };
    let jitter = match a.jitter {
        None => None,
        Some(j) if (0.0..1.0).contains(&j) => Some(ColorJitter {
            brightness: j,
            contrast: j,
            saturation: j,
        }),
        Some(j) => {
            return Err(bad(
                cfg,
                "train.augment.jitter",
                format!("must be in [0, 1), got {j}"),
            ))
        }
    };
    Ok(Augment {
        hflip: a.hflip.unwrap_or(false),
        jitter,
    })
}

/// `[optimizer]`.
fn resolve_adam(cfg: &Path, o: &RawOptimizer) -> Result<AdamConfig> {
    if !(o.lr > 0.0 && o.lr.is_finite()) {
        return Err(bad(
            cfg,
            "optimizer.lr",
            format!("must be positive, got {}", o.lr),
        ));
    }
    let adam = AdamConfig {
        betas: o.betas.unwrap_or([0.9, 0.999]),
        eps: o.eps.unwrap_or(1e-8),
        weight_decay: o.weight_decay.unwrap_or(0.0),
        decoupled: o.kind == Some(OptimizerName::Adamw),
    };
    if !adam.betas.iter().all(|b| (0.0..1.0).contains(b)) {
        return Err(bad(cfg, "optimizer.betas", "each must be in [0, 1)".into()));
    }
    if !positive(adam.eps) || adam.weight_decay.is_nan() || adam.weight_decay < 0.0 {
        return Err(bad(
            cfg,
            "optimizer",
            "eps must be positive and weight_decay non-negative".into(),
        ));
    }
    Ok(adam)
}

/// `[schedule]` from the base learning rate `lr` (constant if absent); a key the kind does not
/// use is an error.
fn resolve_schedule(cfg: &Path, lr: f64, schedule: Option<RawSchedule>) -> Result<Schedule> {
    let Some(s) = schedule else {
        return Ok(Schedule::constant(lr));
    };
    let unused = |key: &str, v: bool| -> Result<()> {
        if v {
            Err(bad(
                cfg,
                &format!("schedule.{key}"),
                format!("does not apply to kind = {:?}", s.kind),
            ))
        } else {
            Ok(())
        }
    };
    let decay = match s.kind {
        ScheduleName::Constant => {
            unused("every", s.every.is_some())?;
            unused("gamma", s.gamma.is_some())?;
            unused("min_lr", s.min_lr.is_some())?;
            Decay::Constant
        }
        ScheduleName::Step => {
            unused("min_lr", s.min_lr.is_some())?;
            let every = s.every.filter(|&e| e > 0).ok_or_else(|| {
                bad(
                    cfg,
                    "schedule.every",
                    "a positive step count is required".into(),
                )
            })?;
            let gamma = s.gamma.unwrap_or(0.1);
            if !positive(gamma) {
                return Err(bad(cfg, "schedule.gamma", "must be positive".into()));
            }
            Decay::Step { every, gamma }
        }
        ScheduleName::Cosine => {
            unused("every", s.every.is_some())?;
            unused("gamma", s.gamma.is_some())?;
            let min_lr = s.min_lr.unwrap_or(0.0);
            if !(0.0..=lr).contains(&min_lr) {
                return Err(bad(
                    cfg,
                    "schedule.min_lr",
                    format!("must be in [0, lr = {lr}]"),
                ));
            }
            Decay::Cosine { min_lr }
        }
    };
    Ok(Schedule {
        lr,
        warmup: s.warmup.unwrap_or(0),
        decay,
    })
}

/// `[train]`, `[optimizer]` and `[schedule]`.
fn resolve_train(
    cfg: &Path,
    task: Task,
    t: RawTrain,
    o: RawOptimizer,
    schedule: Option<RawSchedule>,
) -> Result<TrainSpec> {
    let length = match (t.epochs, t.steps) {
        (Some(e), None) if e > 0 => Length::Epochs(e),
        (None, Some(s)) if s > 0 => Length::Steps(s),
        _ => {
            return Err(bad(
                cfg,
                "train",
                "give exactly one of `epochs` and `steps`, positive".into(),
            ))
        }
    };
    if t.batch_size == 0 {
        return Err(bad(cfg, "train.batch_size", "must be positive".into()));
    }
    let eval_batch_size = t.eval_batch_size.unwrap_or(t.batch_size);
    if eval_batch_size == 0 {
        return Err(bad(cfg, "train.eval_batch_size", "must be positive".into()));
    }
    let depth_loss = resolve_loss(cfg, task, t.loss)?;
    let val_metric = resolve_val_metric(cfg, task, t.val_metric.as_deref())?;
    for (f, v) in [
        ("train.val_every", t.val_every),
        ("train.log_every", t.log_every),
        ("train.checkpoint_every", t.checkpoint_every),
    ] {
        if v == Some(0) {
            return Err(bad(cfg, f, "must be positive".into()));
        }
    }
    let augment = resolve_augment(cfg, t.augment.as_ref())?;
    let radial_bins = t.radial_bins.unwrap_or(16);
    if radial_bins == 0 {
        return Err(bad(cfg, "train.radial_bins", "must be positive".into()));
    }
    let adam = resolve_adam(cfg, &o)?;
    let schedule = resolve_schedule(cfg, o.lr, schedule)?;
    Ok(TrainSpec {
        length,
        batch_size: t.batch_size,
        eval_batch_size,
        depth_loss,
        val_every: t.val_every,
        val_metric,
        log_every: t.log_every.unwrap_or(20),
        checkpoint_every: t.checkpoint_every,
        images: t.images.unwrap_or(4),
        radial_bins,
        augment,
        adam,
        schedule,
    })
}

/// What every `[[eval]]` inherits from the experiment.
struct EvalDefaults<'a> {
    cfg: &'a Path,
    root: &'a Path,
    kernel: KernelName,
    model: &'a UNetConfig,
    input: &'a InputSpec,
    /// `input.width`.
    width: Option<usize>,
    train: &'a TrainSpec,
}

impl EvalDefaults<'_> {
    /// The input of an evaluation with these `camera` / `padding` / `size` / `convention` keys.
    ///
    /// A camera of another image size gets its own defaults (no padding, its own size); the
    /// same camera, or one with the same image size, keeps the input's padding, and its size if
    /// the padding is kept too.
    fn input(&self, field: &str, e: &RawEval) -> Result<InputSpec> {
        let input = self.input;
        let (cam, pad, size, conv) = match (&e.camera, e.padding, e.size, e.convention) {
            (None, None, None, None) => return Ok(input.clone()),
            other => other,
        };
        let cam_path = match cam {
            Some(c) => absolute(c)?,
            None => input.camera_file.clone(),
        };
        let same = cam_path == input.camera_file
            || camera::load(&cam_path).is_ok_and(|c| {
                let s = self.width.map_or(1.0, |w| w as f64 / c.size()[0] as f64);
                let scaled = c.rescaled([s, s], PixelConvention::HalfPixel);
                scaled.size() == input.camera.size()
            });
        let size = size.or((same && pad.is_none()).then_some(input.size));
        let pad = pad.or(same.then_some(input.padding));
        input_spec(
            self.cfg,
            field,
            &cam_path,
            self.width,
            pad,
            size,
            conv.or(Some(input.convention)),
        )
    }

    /// `eval[k]`; `done` are the evaluations before it (their names must differ).
    fn resolve(&self, k: usize, e: RawEval, done: &[EvalSpec]) -> Result<EvalSpec> {
        let cfg = self.cfg;
        let f = |key: &str| format!("eval[{k}].{key}");
        check_name(cfg, &f("name"), &e.name)?;
        if done.iter().any(|d| d.name == e.name) {
            return Err(bad(cfg, &f("name"), format!("`{}` is used twice", e.name)));
        }
        let data = e.data.clone().resolve(cfg, &f("data"), self.root)?;
        let kernel = e.kernel.unwrap_or(self.kernel);
        let input = self.input(&f("camera"), &e)?;
        if kernel.uses_camera() {
            check_calibrated(cfg, &f("size"), self.model, &input)?;
        }
        let radial_bins = e.radial_bins.unwrap_or(self.train.radial_bins);
        if radial_bins == 0 {
            return Err(bad(cfg, &f("radial_bins"), "must be positive".into()));
        }
        if let Some(r) = e.radial_max {
            if !positive(r) {
                return Err(bad(cfg, &f("radial_max"), "must be positive".into()));
            }
        }
        let batch_size = e.batch_size.unwrap_or(self.train.eval_batch_size);
        if batch_size == 0 {
            return Err(bad(cfg, &f("batch_size"), "must be positive".into()));
        }
        Ok(EvalSpec {
            name: e.name,
            data,
            kernel,
            input,
            radial_bins,
            radial_max: e.radial_max,
            images: e.images.unwrap_or(4),
            batch_size,
        })
    }
}

impl RawEval {
    /// The evaluation of an experiment without `[[eval]]`: `data.test` with the model's kernel
    /// and the `[input]` camera.
    fn test(data: RawSource) -> RawEval {
        RawEval {
            name: "test".into(),
            data,
            kernel: None,
            camera: None,
            padding: None,
            size: None,
            convention: None,
            radial_bins: None,
            radial_max: None,
            images: None,
            batch_size: None,
        }
    }
}

impl RawExperiment {
    /// Checks every value and fills in the defaults; `path` is the file (for relative-path
    /// errors and the record), `text` its content.
    pub fn resolve(self, path: &Path, text: &str) -> Result<Experiment> {
        let cfg = path;
        check_name(cfg, "name", &self.name)?;
        let device = self.device.unwrap_or_else(|| "auto".to_string());
        parse_device(&device).map_err(|e| bad(cfg, "device", e.to_string()))?;

        let model = resolve_model(cfg, self.task, &self.model)?;
        let kernel = self.model.kernel;
        let init = resolve_init(cfg, &self.name, self.model.init)?;

        // Input.
        let i = self.input;
        let width = i.width;
        let input = input_spec(
            cfg,
            "input.camera",
            &i.camera,
            width,
            i.padding,
            i.size,
            i.convention,
        )?;
        if kernel.uses_camera() {
            check_calibrated(cfg, "input.size", &model, &input)?;
        }

        // Data.
        let root = self.data_root.unwrap_or_else(|| PathBuf::from("."));
        let root = root.as_path();
        let train_data = self.data.train.resolve(cfg, "data.train", root)?;
        let val_data = self
            .data
            .val
            .map(|s| s.resolve(cfg, "data.val", root))
            .transpose()?;
        let raw_test = self.data.test.clone();
        let test_data = self
            .data
            .test
            .map(|s| s.resolve(cfg, "data.test", root))
            .transpose()?;

        let train = resolve_train(cfg, self.task, self.train, self.optimizer, self.schedule)?;

        // Output.
        let output = absolute(&self.output.unwrap_or_else(|| PathBuf::from(DEFAULT_OUTPUT)))?;
        let run_dir = output.join(&self.name);
        let init = init.map(|(name, file)| match file {
            Some(f) => InitSpec::Checkpoint(f),
            None => InitSpec::Experiment {
                checkpoints: layout::RunDir::new(output.join(&name)).checkpoints(),
                name,
            },
        });

        // Evaluations (default: the test split with the model's kernel).
        let mut raw_evals = self.evals;
        if raw_evals.is_empty() {
            raw_evals.extend(raw_test.map(RawEval::test));
        }
        let defaults = EvalDefaults {
            cfg,
            root,
            kernel,
            model: &model,
            input: &input,
            width,
            train: &train,
        };
        let mut evals = Vec::new();
        for (k, e) in raw_evals.into_iter().enumerate() {
            let spec = defaults.resolve(k, e, &evals)?;
            evals.push(spec);
        }

        Ok(Experiment {
            name: self.name,
            description: self.description,
            file: absolute(path)?,
            text: text.to_string(),
            seed: self.seed.unwrap_or(0),
            run_dir,
            output,
            device,
            model,
            kernel,
            init,
            input,
            train_data,
            val_data,
            test_data,
            train,
            evals,
        })
    }
}
