//! `calibconv report RESULTS [--out DIR]`: the library's report, plus a point cloud from the
//! predicted and true depth of one test image (it needs a network, so it is built here, where
//! the experiment and report layers meet).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

use calibconv::experiment::layout::{Replicate, ResultsDir};
use calibconv::experiment::{self, run, SourceRequest};
use calibconv::report::pointcloud::{back_project, top_view, write_ply};
use calibconv::report::results::{write_report_with, ReportOptions};

use crate::cli::ReportArgs;

pub fn run(args: ReportArgs) -> Result<()> {
    let out = args.out.clone().unwrap_or_else(|| args.results.clone());
    warn_unused_runs(&args.results)?;
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    match point_cloud(&args.results, &out, !args.no_ply) {
        Ok(Some(run)) => println!("point cloud of the first test image of {run}"),
        Ok(None) => {}
        Err(e) => eprintln!("warning: no point cloud: {e:#}"),
    }
    let opts = ReportOptions {
        averaging: args.averaging,
        bootstrap_seed: args.bootstrap_seed,
    };
    let written = write_report_with(&args.results, &out, &opts)
        .with_context(|| format!("cannot report on {}", args.results.display()))?;
    for f in &written {
        println!("wrote {}", f.display());
    }
    // The verdict table is what a reader came for: print it.
    let verdict = out.join("verdict.md");
    let text = std::fs::read_to_string(&verdict)
        .with_context(|| format!("cannot read {}", verdict.display()))?;
    println!("\n{text}");
    println!("report: {}", out.join("REPORT.md").display());
    Ok(())
}

/// With `seed-S/` replicates the report reads only them: say so when run directories sit at
/// the top level too (an older single-seed sweep into the same folder), instead of ignoring
/// them silently.
fn warn_unused_runs(results: &Path) -> Result<()> {
    let dir = ResultsDir::new(results);
    let replicates = dir.replicates()?;
    if replicates.iter().all(|r| r.seed.is_none()) {
        return Ok(());
    }
    let top = Replicate {
        seed: None,
        dir: results.to_path_buf(),
    };
    let unused = ResultsDir::runs(&top)?;
    if !unused.is_empty() {
        let names: Vec<String> = unused
            .iter()
            .filter_map(|r| {
                r.path()
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
            })
            .collect();
        eprintln!(
            "warning: {} has seed-S/ replicates; the report ignores the {} run directories at its top level ({})",
            results.display(),
            names.len(),
            names.join(", ")
        );
    }
    Ok(())
}

/// The depth run to show: a fine-tuned calibrated one, the widest field of view first (of the
/// first seed replicate).
fn pick_run(results: &Path) -> Option<PathBuf> {
    // With seed replicates, the first seed's.
    let first = calibconv::report::collect::replicates(results)
        .ok()?
        .into_iter()
        .next()?;
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&first.dir)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("summary.json").is_file())
        .collect();
    dirs.sort();
    for want in ["depth-ft-f195-calibrated", "depth-ft-f165-calibrated"] {
        if let Some(d) = dirs.iter().find(|d| {
            d.file_name()
                .is_some_and(|n| n.to_string_lossy().ends_with(want))
        }) {
            return Some(d.clone());
        }
    }
    None
}

fn to_vec(t: &Tensor) -> Result<Vec<f32>> {
    Ok(Vec::<f32>::try_from(
        t.to_kind(Kind::Float).contiguous().flatten(0, -1),
    )?)
}

/// `pointcloud_{pred,true}.ply` (unless `ply` is false: then earlier ones are removed) and
/// `pointcloud_top.png` in `out`; the run's name, or `None` when there is no fine-tuned
/// calibrated depth run.
fn point_cloud(results: &Path, out: &Path, ply: bool) -> Result<Option<String>> {
    let Some(dir) = pick_run(results) else {
        return Ok(None);
    };
    let file = dir.join("experiment.toml");
    let text = std::fs::read_to_string(&file)?;
    let exp = experiment::parse(&text, &file)?
        .resolve(&file, &text)
        .with_context(|| {
            format!(
                "{} (run the report from the sweep's folder)",
                file.display()
            )
        })?;
    let Some(spec) = exp
        .test_data
        .clone()
        .or(exp.evals.first().map(|e| e.data.clone()))
    else {
        bail!("{}: no test data", exp.name);
    };
    let vs = VarStore::new(Device::Cpu);
    let model = run::build_model(&exp, &vs, exp.kernel, &exp.input)?;
    let ckpt = run::best_or_last(&run::checkpoint_dir(&exp))
        .with_context(|| format!("{}: no checkpoint", exp.name))?;
    calibconv::train::checkpoint::load(&ckpt, &vs, &exp.model)?;
    let source = experiment::open_source(&SourceRequest {
        spec: &spec,
        batch_size: 1,
        shuffle: None,
        input_size: exp.input.size,
        camera: &exp.input.camera,
        frame: exp.input.frame(),
        augment: Default::default(),
    })?;
    let batch = source.batches(0, 0).next().context("empty test split")??;
    let pred = tch::no_grad(|| model.f_forward_t(&batch.image, false))?;
    let [h, w] = [exp.input.size[0] as usize, exp.input.size[1] as usize];
    let rgb: Vec<f32> = to_vec(&batch.image.get(0).permute([1, 2, 0]))?;
    let byte = |x: f32| (x * 255.0).round().clamp(0.0, 255.0) as u8;
    let rgb: Vec<[u8; 3]> = rgb
        .chunks(3)
        .map(|c| [byte(c[0]), byte(c[1]), byte(c[2])])
        .collect();
    let mask: Vec<bool> = to_vec(&batch.mask)?.into_iter().map(|m| m > 0.5).collect();
    let truth: Vec<f32> = to_vec(&batch.depth)?;
    let predicted: Vec<f32> = to_vec(&pred)?;
    let cam = &exp.input.camera;
    let p = back_project(cam, [h, w], &predicted, &mask, &rgb);
    let t = back_project(cam, [h, w], &truth, &mask, &rgb);
    for (name, points) in [("pointcloud_pred.ply", &p), ("pointcloud_true.ply", &t)] {
        let path = out.join(name);
        if ply {
            write_ply(&path, points)?;
        } else if path.is_file() {
            std::fs::remove_file(&path)
                .with_context(|| format!("cannot remove {}", path.display()))?;
            println!("removed {} (--no-ply)", path.display());
        }
    }
    top_view(
        &out.join("pointcloud_top.png"),
        &[(&t, [110, 110, 110]), (&p, [31, 119, 180])],
        512,
    )?;
    let about = format!(
        "run {}, checkpoint {}, test image {}",
        exp.name,
        ckpt.display(),
        batch.ids.first().cloned().unwrap_or_default()
    );
    std::fs::write(out.join("pointcloud.txt"), &about)?;
    Ok(Some(exp.name))
}
