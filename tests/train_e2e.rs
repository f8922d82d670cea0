//! End to end on the built-in toy task: an experiment file trains with each kernel kind, writes
//! its run directory, evaluates, and its checkpoint reloads into a fresh network that gives the
//! same metrics; an interrupted run resumes to the same weights as an uninterrupted one; a NaN
//! stops training with the last good checkpoint intact; the binary runs `train` and `eval`.
//!
//! Tests run in parallel threads and libtorch's random generator is global: every network here
//! is built through `train::seeded` (which holds a lock) and nothing else draws random numbers,
//! so initial weights depend on the seeds only. Hence a test binary of its own: the tests of
//! `tests/integration/` draw from that generator freely (and reseed it).

mod common;

use std::path::{Path, PathBuf};

use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use calibconv::data::memory::MemorySource;
use calibconv::eval::metrics::Metric;
use calibconv::experiment::{self, RunOptions};
use calibconv::nn::{ConvKind, Head, UNet, UNetConfig};
use calibconv::train::adam::AdamConfig;
use calibconv::train::checkpoint::{self, TensorFile};
use calibconv::train::schedule::Schedule;
use calibconv::train::{self, Length, NoReporter, TrainConfig, TrainRun};
use calibconv::Error;
use common::experiment::{quiet, ExperimentFile};
use common::{assert_contains, failed, ok};

/// A toy experiment in `dir`: F195 padded to a square and scaled to 48x48, tiny U-Net, `steps`
/// steps of batches of 4, validated every 12.
fn experiment(dir: &Path, name: &str, kernel: &str, steps: u32) -> ExperimentFile {
    ExperimentFile::tiny(name)
        .set("seed", 3)
        .set_path("output", dir)
        .set("model.kernel", kernel)
        .square(48)
        .set_toml("data.train", r#"{ toy = 16, split = "train" }"#)
        .set_toml("data.val", r#"{ toy = 4, split = "val" }"#)
        .set_toml("data.test", r#"{ toy = 4, split = "test" }"#)
        .set("train.steps", steps)
        .set("train.batch_size", 4)
        .set("train.log_every", 4)
        .set("train.val_every", 12)
        .set("train.images", 2)
        .set("train.radial_bins", 4)
        .set("optimizer.lr", 1e-2)
}

fn vars(path: &Path) -> Vec<(String, Tensor)> {
    let mut v = Tensor::read_safetensors(path).unwrap();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[test]
fn each_kernel_kind_trains_evaluates_and_reloads() {
    for kernel in ["standard", "calibrated"] {
        let dir = tempfile::tempdir().unwrap();
        let exp = experiment(dir.path(), "e2e", kernel, 24).load_in(dir.path());
        let out = experiment::train(&exp, &quiet()).unwrap();
        let s = &out.summary;
        assert_eq!(s.steps, 24, "{kernel}");
        // Observed 4.69 -> 2.86 (standard) and 4.69 -> 2.87 (calibrated).
        assert!(
            s.last_loss < 0.8 * s.first_loss,
            "{kernel}: loss {} -> {}",
            s.first_loss,
            s.last_loss
        );
        // Validations at steps 12 and 24; the best checkpoint is one of them.
        assert_eq!(s.validations.len(), 2, "{kernel}");
        let (metric, best, best_step) = s.best.unwrap();
        assert_eq!(metric, Metric::Rmse);
        assert!(best_step == 12 || best_step == 24);

        let run = &exp.run_dir;
        for f in [
            "experiment.toml",
            "config.json",
            "run.json",
            "summary.json",
            "train.csv",
            "val.csv",
            "evaluations.csv",
            "checkpoints/last.safetensors",
            "checkpoints/last.optim.safetensors",
            "checkpoints/best.safetensors",
            "eval/test/metrics.json",
            "eval/test/metrics.csv",
            "eval/test/radial.csv",
            "eval/test/radial_rmse.png",
            "eval/test/radial_delta1.png",
        ] {
            assert!(run.join(f).is_file(), "{kernel}: no {f}");
        }
        let pngs = std::fs::read_dir(run.join("eval/test/predictions"))
            .unwrap()
            .count();
        assert_eq!(pngs, 4, "{kernel}");
        let events = std::fs::read_dir(run.join("tb")).unwrap().count();
        assert_eq!(events, 1, "{kernel}");
        let val_csv = std::fs::read_to_string(run.join("val.csv")).unwrap();
        assert!(
            val_csv.starts_with("step,loss,mre,mae,rmse,rmse_log,delta1"),
            "{val_csv}"
        );
        assert_eq!(val_csv.lines().count(), 3);
        let radial = std::fs::read_to_string(run.join("eval/test/radial.csv")).unwrap();
        assert_eq!(radial.lines().count(), 1 + 4);

        // The checkpoint records what produced it.
        let best_file = run.join("checkpoints/best.safetensors");
        let info = TensorFile::open(&best_file)
            .unwrap()
            .info()
            .unwrap()
            .unwrap();
        assert_eq!(info.kernel, kernel);
        assert_eq!(info.step, best_step);
        assert_eq!(info.input_size, [48, 48]);
        assert!(info.camera_toml.unwrap().contains("fov_deg = 195.0"));
        assert!((info.metrics["rmse"] - best).abs() < 1e-12);

        // Reload into a fresh network (other initial weights): the weights are the file's, and
        // evaluating again gives the same numbers.
        let mut other = exp.clone();
        other.seed = 99;
        let vs = VarStore::new(Device::Cpu);
        experiment::run::build_model(&other, &vs, exp.evals[0].kernel, &exp.input).unwrap();
        checkpoint::load(&best_file, &vs, &exp.model).unwrap();
        for (name, t) in vars(&best_file) {
            assert!(vs.variables()[&name].equal(&t), "{kernel}: {name}");
        }
        let written = &out.evaluations[0].evaluation;
        let again = experiment::evaluate(&exp, Some(&best_file), &[], &quiet()).unwrap();
        for ((m, a), (_, b)) in written.metrics.iter().zip(&again[0].evaluation.metrics) {
            assert!(
                (a - b).abs() <= 1e-9 * a.abs().max(1.0),
                "{kernel} {m}: {a} vs {b}"
            );
        }

        // Training the same run again without --resume is refused.
        let e = experiment::train(&exp, &quiet()).unwrap_err().to_string();
        assert!(e.contains("already has checkpoints"), "{e}");
    }
}

#[test]
fn resume_continues_at_the_same_step_with_the_same_data_order() {
    let dir = tempfile::tempdir().unwrap();
    let run =
        |d: &Path, steps| experiment(d, "r", "standard", steps).set("train.checkpoint_every", 2);
    // Uninterrupted: 10 steps (4 per epoch, so the stop at 6 is mid-epoch).
    let a_dir = dir.path().join("a");
    let a = run(&a_dir, 10).load_in(&mkdir(&a_dir));
    experiment::train(&a, &quiet()).unwrap();
    // Interrupted after 6 steps (the same file with steps = 6), then resumed to 10.
    let b_dir = dir.path().join("b");
    let b6 = run(&b_dir, 6).load_in(&mkdir(&b_dir));
    experiment::train(&b6, &quiet()).unwrap();
    let info = TensorFile::open(&b6.run_dir.join("checkpoints/last.safetensors"))
        .unwrap()
        .info()
        .unwrap()
        .unwrap();
    assert_eq!((info.step, info.epoch, info.batch_in_epoch), (6, 1, 2));
    let b = run(&b_dir, 10).load_in(&b_dir);
    let resume = RunOptions {
        resume: true,
        ..quiet()
    };
    // Another batch size would change the data order: refused, and the run is left alone.
    let other = run(&b_dir, 10).set("train.batch_size", 2).load_in(&b_dir);
    let e = experiment::train(&other, &resume).unwrap_err().to_string();
    assert!(e.contains("batch size 4, not 2"), "{e}");
    let stored = std::fs::read_to_string(b.run_dir.join("experiment.toml")).unwrap();
    assert!(stored.contains("steps = 6"));
    let out = experiment::train(&b, &resume).unwrap();
    assert_eq!((out.summary.steps, out.summary.steps_this_run), (10, 4));
    let (va, vb) = (
        vars(&a.run_dir.join("checkpoints/last.safetensors")),
        vars(&b.run_dir.join("checkpoints/last.safetensors")),
    );
    assert_eq!(va.len(), vb.len());
    for ((na, ta), (nb, tb)) in va.iter().zip(&vb) {
        assert_eq!(na, nb);
        assert!(ta.equal(tb), "{na} differs after resume");
    }
    // The CSV log holds every step once.
    let steps: Vec<String> = std::fs::read_to_string(b.run_dir.join("train.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().to_string())
        .collect();
    assert_eq!(steps, ["4", "6", "8", "10"]);
}

/// Creates `d` and returns it.
fn mkdir(d: &Path) -> PathBuf {
    std::fs::create_dir_all(d).unwrap();
    d.to_path_buf()
}

#[test]
fn a_nan_stops_training_and_keeps_the_last_good_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    // 8 samples in order, batches of 2: the fourth batch (samples 6, 7) holds a NaN pixel.
    let (n, h, w) = (8i64, 16i64, 16i64);
    // No random numbers: the other tests of this binary rely on seeded initialisation.
    let image = (Tensor::arange(n * 3 * h * w, (Kind::Float, Device::Cpu)) * 0.37)
        .sin()
        .abs()
        .view([n, 3, h, w]);
    let _ = image.get(6).get(0).get(3).get(3).fill_(f64::NAN);
    let source = MemorySource::new(
        image,
        Tensor::ones([n, 1, h, w], (Kind::Float, Device::Cpu)) * 2.0,
        Tensor::zeros([n, h, w], (Kind::Int64, Device::Cpu)),
        Tensor::ones([n, 1, h, w], (Kind::Bool, Device::Cpu)),
        (0..n).map(|i| format!("s{i}")).collect(),
        2,
        None,
    )
    .unwrap();
    let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
    let vs = VarStore::new(Device::Cpu);
    let model = train::seeded(0, || {
        UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [h, w])
    })
    .unwrap();
    let info = common::checkpoint_info(cfg, [h, w]);
    let tc = TrainConfig {
        length: Length::Steps(8),
        batch_size: 2,
        adam: AdamConfig::default(),
        schedule: Schedule::constant(1e-3),
        depth_loss: Default::default(),
        val_every: None,
        val_metric: Metric::Rmse,
        log_every: 1,
        checkpoint_every: Some(2),
        device: Device::Cpu,
        progress: false,
        verbose: false,
        stop: train::stop::StopFlag::detached(),
    };
    let err = train::train(
        TrainRun {
            model: &model,
            vs: &vs,
            train: &source,
            val: None,
            checkpoint_dir: dir.path(),
            info,
            reporter: &mut NoReporter,
            resume: false,
        },
        &tc,
    )
    .unwrap_err();
    let last = dir.path().join("last.safetensors");
    match &err {
        Error::NonFinite {
            step,
            what,
            last_good,
            ..
        } => {
            assert_eq!(*step, 4);
            assert_eq!(what, "training loss");
            assert_eq!(last_good.as_deref(), Some(last.as_path()));
        }
        other => panic!("expected NonFinite, got {other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("step 4") && msg.contains("last.safetensors"),
        "{msg}"
    );
    // The last good checkpoint is from step 2 and loads, with finite weights.
    let vs2 = VarStore::new(Device::Cpu);
    train::seeded(1, || {
        UNet::new(&vs2.root(), &cfg, &ConvKind::Standard, [h, w])
    })
    .unwrap();
    let loaded = checkpoint::load(&last, &vs2, &cfg).unwrap();
    assert_eq!(loaded.info.unwrap().step, 2);
    for (name, t) in vs2.variables() {
        assert_eq!(t.isfinite().all().int64_value(&[]), 1, "{name}");
    }
}

#[test]
fn the_binary_trains_and_evaluates_and_names_a_wrong_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let cli = experiment(dir.path(), "cli", "standard", 4);
    let file = cli.write(&dir.path().join("cli.toml"));
    let run = common::calibconv;
    let f = common::s(&file);
    let stdout = common::stdout(&ok(run(&["train", f, "--quiet"])));
    assert!(stdout.contains("cli: 4 steps"), "{stdout}");
    let o = ok(run(&["eval", f, "--quiet", "--only", "test"]));
    assert!(common::stdout(&o).contains("test: loss"));
    // A checkpoint of another architecture (a small U-Net) is refused, naming a tensor.
    let other = dir.path().join("other.safetensors");
    let vs = VarStore::new(Device::Cpu);
    train::seeded(0, || {
        UNet::new(
            &vs.root(),
            &UNetConfig::preset("small", Head::Depth).unwrap(),
            &ConvKind::Standard,
            [48, 48],
        )
    })
    .unwrap();
    checkpoint::write_tensors(
        &other,
        &checkpoint::named_variables(&vs),
        Default::default(),
    )
    .unwrap();
    let stderr = failed(run(&[
        "eval",
        f,
        "--quiet",
        "--checkpoint",
        common::s(&other),
    ]));
    assert_contains(
        &stderr,
        &[
            "other.safetensors",
            "does not fit this network",
            "`down1.maxpool_conv.1.double_conv.0.weight`",
        ],
    );
    // Unknown evaluation names get a suggestion; a typo in the file names the key.
    let o = run(&["eval", f, "--only", "tset"]);
    assert!(common::stderr(&o).contains("did you mean `test`"));
    let typo = cli.remove("train.batch_size").set("train.batch_sise", 4);
    typo.write(&file);
    let o = run(&["train", f]);
    assert_contains(
        &common::stderr(&o),
        &["train.batch_sise", "did you mean `batch_size`"],
    );
}

#[test]
fn segmentation_trains_and_reports_per_class_scores() {
    let dir = tempfile::tempdir().unwrap();
    let exp = experiment(dir.path(), "seg", "standard", 16)
        .set("task", "segmentation")
        .set("train.loss", "cross-entropy")
        .load_in(dir.path());
    assert_eq!(exp.train.val_metric, Metric::MIoU);
    let out = experiment::train(&exp, &quiet()).unwrap();
    let s = &out.summary;
    // Cross-entropy over 13 classes starts near ln 13 = 2.56. Observed 2.76 -> 1.92.
    assert!(s.first_loss > 1.5, "{}", s.first_loss);
    assert!(
        s.last_loss < 0.8 * s.first_loss,
        "loss {} -> {}",
        s.first_loss,
        s.last_loss
    );
    let e = &out.evaluations[0].evaluation;
    for m in [Metric::MIoU, Metric::MAcc, Metric::PixelAcc] {
        let v = e.metric(m).unwrap();
        assert!((0.0..=1.0).contains(&v), "{m} {v}");
    }
    let doc: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(exp.run_dir.join("eval/test/metrics.json")).unwrap(),
    )
    .unwrap();
    assert!(doc["classes"]["wall"]["pixels"].is_u64(), "{doc}");
    let radial = std::fs::read_to_string(exp.run_dir.join("eval/test/radial.csv")).unwrap();
    assert!(radial.starts_with("bin,r_lo,r_hi,pixels,images,miou,miou_mean,miou_std,macc"));
}
