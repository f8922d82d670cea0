//! The report of a sweep's output folder (`calibconv report RESULTS`): the paper's tables with
//! intervals over seeds, the paired-difference table, radial plots with bands over seeds,
//! qualitative grids, the computed verdict on the paper's claims and `REPORT.md`, read from
//! the run directories of every seed ([`super::collect`]).
//!
//! Files in `out` (default: `RESULTS`): `table_{depth,seg}.{md,csv}` (each cell mean ± 95%
//! Student-t half-width over seeds, with n), `differences_{depth,seg}.{md,csv}` (paired
//! differences per seed, their mean and t-interval over seeds, and per seed a paired bootstrap
//! interval over test images), `radial_TASK_BLOCK_SET_METRIC.png`, `grid_TASK_BLOCK_SET.png`
//! ([`super::grids`]), `verdict.json` / `verdict.md` ([`super::verdict`]), `training.md`,
//! `runs.md` and `REPORT.md` (the verdict, the two tables and the figures, linking the rest). Depth tables use
//! [`ReportOptions::averaging`] (default `per-image`, the authors' convention) and say so;
//! segmentation uses one confusion matrix over the test set. The best mean of each metric
//! among the rows of one block and data set (one calibration) is bold.

use std::path::{Path, PathBuf};

use super::collect::{collect, Row, Study};
use super::grids::{qualitative_grids, COLUMNS};
use super::radial::radial_plots;
use super::study::Observations;
use super::study::Task;
use super::tables::{
    cell_table, comparison_pairs, convention, difference_table, seed_values_csv,
    BOOTSTRAP_RESAMPLES,
};
use super::verdict::{markdown, verdict, Meta, CLAIM_DATASETS};
use crate::error::{Error, Result};
use crate::eval::metrics::{Averaging, Metric, DEPTH_METRICS, SEGMENTATION_METRICS};
use crate::io::write_bytes_atomic;

/// How to report.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReportOptions {
    /// Depth metrics' averaging in the tables, differences and verdict.
    pub averaging: Averaging,
    /// Seed of the bootstrap over test images (seed `s` of the study resamples with
    /// `bootstrap_seed + s`).
    pub bootstrap_seed: u64,
}

impl Default for ReportOptions {
    fn default() -> Self {
        ReportOptions {
            averaging: Averaging::PerImage,
            bootstrap_seed: 0,
        }
    }
}

/// The class palette legend as Markdown (colour swatches are the hex values of
/// [`crate::eval::visual::PALETTE`]).
fn legend_md() -> String {
    let mut s = String::from("| class | colour |\n|---|---|\n");
    for (i, c) in crate::data::CLASSES.iter().enumerate() {
        let [r, g, b] = crate::eval::visual::PALETTE[i];
        s += &format!("| {c} | `#{r:02x}{g:02x}{b:02x}` |\n");
    }
    s
}

/// `path` relative to the folder `base` (`..` where needed), for links in `REPORT.md`.
fn rel(path: &Path, base: &Path) -> String {
    let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let (p, b) = (abs(path), abs(base));
    let pc: Vec<_> = p.components().collect();
    let bc: Vec<_> = b.components().collect();
    let common = pc.iter().zip(&bc).take_while(|(x, y)| x == y).count();
    let mut out = PathBuf::new();
    for _ in common..bc.len() {
        out.push("..");
    }
    for c in &pc[common..] {
        out.push(c);
    }
    out.display().to_string()
}

/// [`write_report_with`] with the default options.
pub fn write_report(results: &Path, out: &Path) -> Result<Vec<PathBuf>> {
    write_report_with(results, out, &ReportOptions::default())
}

fn link(path: &Path, out: &Path) -> String {
    let r = rel(path, out);
    format!("[{r}]({r})")
}

/// What every section of the report reads.
struct Ctx<'a> {
    study: &'a Study,
    obs: &'a Observations,
    opts: &'a ReportOptions,
    out: &'a Path,
}

/// The verdict: writes `verdict.json` and `verdict.md`, returns its `REPORT.md` section.
fn verdict_section(cx: &Ctx<'_>, files: &mut Vec<PathBuf>) -> Result<String> {
    let Ctx {
        study,
        obs,
        opts,
        out,
    } = *cx;
    let in_claims = |r: &super::collect::RunInfo| study.evaluates_on(r, &CLAIM_DATASETS);
    let v = verdict(
        obs,
        &Meta {
            profile: study.profile(),
            test_images: study.test_images(),
            averaging: opts.averaging,
            wall_s: study.elapsed_seconds_of(in_claims),
            run_seconds: study
                .runs
                .iter()
                .filter(|r| in_claims(r))
                .filter_map(|r| r.sweep_seconds)
                .sum(),
        },
    );
    let mut verdict_md = markdown(&v);
    let (_, untimed) = study.wall_seconds();
    if untimed > 0 {
        verdict_md += &format!(
            "\n{untimed} run(s) have no `sweep.json` (trained outside a sweep): their time is \
             not in the total.\n"
        );
    }
    if study.shared_baseline() {
        verdict_md += "\nThe BL rows come from one baseline shared by every seed (`study.json`: \
                       `share_baseline`), so C5 has one observation and no interval.\n";
    }
    let verdict_json = super::write_json(&v, out, "verdict.json")?;
    let verdict_file = out.join("verdict.md");
    write_bytes_atomic(&verdict_file, verdict_md.as_bytes())?;
    files.extend([verdict_json.clone(), verdict_file.clone()]);
    Ok(format!(
        "{}\n({}, {})\n\n",
        verdict_md,
        link(&verdict_file, out),
        link(&verdict_json, out)
    ))
}

/// Writes `STEM.md` (`text`) and `STEM.csv` (`csv`) into `out` and adds them to `files`;
/// returns the two files.
fn write_md_csv(
    out: &Path,
    stem: &str,
    text: &str,
    csv: &str,
    files: &mut Vec<PathBuf>,
) -> Result<(PathBuf, PathBuf)> {
    let md_file = out.join(format!("{stem}.md"));
    let csv_file = out.join(format!("{stem}.csv"));
    write_bytes_atomic(&md_file, text.as_bytes())?;
    write_bytes_atomic(&csv_file, csv.as_bytes())?;
    files.extend([md_file.clone(), csv_file.clone()]);
    Ok((md_file, csv_file))
}

/// One task's table, with links to its detail (the table's files, every seed's value, the paired
/// differences); returns its `REPORT.md` section (empty without rows of the task).
fn task_tables(
    cx: &Ctx<'_>,
    task: Task,
    columns: &[Metric],
    title: &str,
    files: &mut Vec<PathBuf>,
) -> Result<String> {
    if !cx.study.rows.iter().any(|r| r.cell.task == task) {
        return Ok(String::new());
    }
    let n_seeds = cx.obs.seeds().len();
    let table = table_section(cx, task, columns, title, n_seeds, files)?;
    let differences = differences_section(cx, task, columns, n_seeds, files)?;
    Ok(format!(
        "{table}Paired differences per seed: {differences}.

"
    ))
}

/// One task's figures (radial plots, qualitative grids of its first seed), with captions.
fn task_figures(cx: &Ctx<'_>, task: Task, files: &mut Vec<PathBuf>) -> Result<String> {
    let seeds: Vec<u64> = cx.obs.seeds().into_iter().collect();
    let first_seed: Vec<&Row> = cx
        .study
        .rows
        .iter()
        .filter(|r| r.cell.task == task && Some(r.seed) == seeds.first().copied())
        .collect();
    let mut report = radial_section(cx, task, seeds.len(), files)?;
    report += &grids_section(cx, task, &first_seed, seeds.first().copied(), files)?;
    Ok(report)
}

/// The task's table of cells over `n_seeds` seeds (`table_T.{md,csv}`, `values_T.csv`).
fn table_section(
    cx: &Ctx<'_>,
    task: Task,
    columns: &[Metric],
    title: &str,
    n_seeds: usize,
    files: &mut Vec<PathBuf>,
) -> Result<String> {
    let Ctx { obs, opts, out, .. } = *cx;
    let title = match task {
        Task::Depth => format!("{title} (metres; `{}` averaging)", opts.averaging),
        Task::Segmentation => format!("{title} (one confusion matrix over the test set)"),
    };
    let about = convention(task, opts.averaging, n_seeds);
    let (md, csv) = cell_table(obs, task, columns);
    let text = format!("## {title}\n\n{about}.\n\n{md}");
    let stem = format!("table_{}", task.short());
    let (md_file, csv_file) = write_md_csv(out, &stem, &text, &csv, files)?;
    let seeds_file = out.join(format!("values_{}.csv", task.short()));
    write_bytes_atomic(&seeds_file, seed_values_csv(obs, task, columns).as_bytes())?;
    files.push(seeds_file.clone());
    Ok(format!(
        "## {title}\n\n{about}.\n\n{md}\nDetail: {}, {}; every seed's value: {}. ",
        link(&md_file, out),
        link(&csv_file, out),
        link(&seeds_file, out)
    ))
}

/// The task's paired differences (`differences_T.{md,csv}`), with a bootstrap over test
/// images when there are two seeds or more; returns the links to the two files.
fn differences_section(
    cx: &Ctx<'_>,
    task: Task,
    columns: &[Metric],
    n_seeds: usize,
    files: &mut Vec<PathBuf>,
) -> Result<String> {
    let Ctx { obs, opts, out, .. } = *cx;
    let pairs = comparison_pairs(obs, task);
    let boot = if n_seeds >= 2 {
        cx.study
            .bootstrap(&pairs, opts.averaging, opts.bootstrap_seed)?
    } else {
        Default::default()
    };
    let (md, csv) = difference_table(obs, &boot, task, columns);
    let diff_about = if n_seeds >= 2 {
        format!(
            "Per seed, the difference of the two rows (the same seed, the same test images); \
             mean and 95% Student-t interval over seeds; per seed in brackets a 95% \
             percentile bootstrap over the test images ({BOOTSTRAP_RESAMPLES} resamples, \
             paired by sample id, seed {} + the study seed): the test-set noise of that seed \
             alone",
            opts.bootstrap_seed
        )
    } else {
        "One seed: the difference of the two rows; intervals need >= 2 seeds".to_string()
    };
    let heading = format!("Paired differences, {}", task.name());
    let text = format!("## {heading}\n\n{diff_about}.\n\n{md}");
    let stem = format!("differences_{}", task.short());
    let (md_file, csv_file) = write_md_csv(out, &stem, &text, &csv, files)?;
    Ok(format!(
        "{} ({})",
        link(&md_file, out),
        link(&csv_file, out)
    ))
}

/// The task's radial plots ([`radial_plots`]), empty if none.
fn radial_section(
    cx: &Ctx<'_>,
    task: Task,
    n_seeds: usize,
    files: &mut Vec<PathBuf>,
) -> Result<String> {
    let plots = radial_plots(cx.study, task, cx.opts.averaging, cx.out)?;
    let mut report = String::new();
    if !plots.is_empty() {
        report += &format!(
            "### Radial plots, {}\n\nMetric vs distance to the principal point ({}); standard \
             kernels red, calibrated blue, rectified green (rectified images are a pinhole \
             projection: the same radius is another viewing angle).\n\n",
            task.name(),
            if n_seeds >= 2 {
                "mean over seeds of each seed's curve, band: 95% Student-t interval over seeds"
            } else {
                "one seed: mean ± 1 std over the test images"
            }
        );
        for p in &plots {
            report += &format!("![{0}]({0})\n", rel(p, cx.out));
        }
        report += "\n";
    }
    files.extend(plots);
    Ok(report)
}

/// The task's qualitative grids from the rows of its first seed `seed`, empty if none.
fn grids_section(
    cx: &Ctx<'_>,
    task: Task,
    rows: &[&Row],
    seed: Option<u64>,
    files: &mut Vec<PathBuf>,
) -> Result<String> {
    let grids = qualitative_grids(rows, cx.out)?;
    let mut report = String::new();
    if !grids.is_empty() {
        report += &format!(
            "### Qualitative results, {}\n\nColumns: {} (the first test images, seed {}).{}\n\n",
            task.name(),
            COLUMNS.join(" | "),
            seed.unwrap_or(0),
            if task == Task::Depth {
                " Depth colour map (the bar under the grid): near dark blue to far yellow, per \
                 image over [0, max ground truth]; invalid pixels black."
            } else {
                " Classes: the fixed palette below; unknown / invalid black."
            }
        );
        for g in &grids {
            report += &format!("![{0}]({0})\n", rel(g, cx.out));
        }
        report += "\n";
        if task == Task::Segmentation {
            report += &legend_md();
            report += "\n";
        }
    }
    files.extend(grids);
    Ok(report)
}

/// Writes the tables, differences, radial plots, grids, verdict and `REPORT.md` of `results`
/// into `out`; returns the files written. `REPORT.md` holds the verdict, the two tables and the
/// figures with their captions, and links to the detail beside it: each table's files and its
/// paired differences per seed, `training.md` (validation curves, timings) and `runs.md` (every
/// run, its time and configuration).
pub fn write_report_with(results: &Path, out: &Path, opts: &ReportOptions) -> Result<Vec<PathBuf>> {
    let study = collect(results)?;
    if study.runs.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "{}: no run directories (folders with experiment.toml, or seed-S/ folders of them); \
             run a sweep first",
            results.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let obs = study.observations(opts.averaging)?;
    let seeds: Vec<u64> = obs.seeds().into_iter().collect();
    let mut files = Vec::new();
    let cx = Ctx {
        study: &study,
        obs: &obs,
        opts,
        out,
    };
    let training = super::curves::training_section(&study, out, &mut files)?;
    let training_file = out.join("training.md");
    write_bytes_atomic(&training_file, training.as_bytes())?;
    let runs_file = out.join("runs.md");
    write_bytes_atomic(&runs_file, runs_section(&study, out).as_bytes())?;
    files.extend([training_file.clone(), runs_file.clone()]);
    let mut report = format!(
        "# Report: {}\n\n{} runs in {} replicate(s) (seeds {:?}), read by `calibconv report` \
         from their run directories (metrics: `RUN/eval/NAME/metrics.json`, per test image: \
         `per_image.json`). Every run, its time and configuration: {}; validation curves and \
         timings: {}.\n\n",
        results.display(),
        study.runs.len(),
        study.replicates.len(),
        seeds,
        link(&runs_file, out),
        link(&training_file, out),
    );
    report += &verdict_section(&cx, &mut files)?;
    let tasks = [
        (Task::Depth, &DEPTH_METRICS[..], "Table 1: depth"),
        (
            Task::Segmentation,
            &SEGMENTATION_METRICS[..],
            "Table 2: semantic segmentation",
        ),
    ];
    for (task, columns, title) in tasks {
        report += &task_tables(&cx, task, columns, title, &mut files)?;
    }
    let mut figures = String::new();
    for (task, ..) in tasks {
        figures += &task_figures(&cx, task, &mut files)?;
    }
    if !figures.is_empty() {
        report += &format!("## Figures\n\n{figures}");
    }
    report += &fov_section(&cx, &mut files)?;
    report += &questions_section(&cx, &mut files)?;
    report += &extra_figures(out);
    report += &training_figures(&files, out);
    let report_file = out.join("REPORT.md");
    write_bytes_atomic(&report_file, report.as_bytes())?;
    files.push(report_file);
    Ok(files)
}

/// The figures other commands left in `out` (the point cloud of `calibconv report`, the kernel
/// grids of `make demo`), with captions.
fn extra_figures(out: &Path) -> String {
    let mut report = String::new();
    if out.join("pointcloud_top.png").is_file() {
        let about = std::fs::read_to_string(out.join("pointcloud.txt")).unwrap_or_default();
        let ply = if out.join("pointcloud_pred.ply").is_file() {
            "; [predicted](pointcloud_pred.ply), [true](pointcloud_true.ply) as PLY"
        } else {
            ""
        };
        report += &format!(
            "## Point cloud\n\nPredicted (blue) and true (grey) depth of one test image \
             back-projected with the camera model (depth = distance along the ray), seen from \
             above, camera at the black dot ({about}){ply}.\n\n![top view](pointcloud_top.png)\n\n"
        );
    }
    for k in ["kernels_f195.png", "kernels_f165.png"] {
        if out.join(k).is_file() {
            report += &format!(
                "## Calibrated kernels\n\nThe sampling positions of calibrated 3x3 kernels over \
                 the image (paper Fig. 1a): ![{k}]({k})\n\n"
            );
        }
    }
    report
}

/// The validation curves among `files` (`val_GROUP.png`), with their caption; empty if none.
fn training_figures(files: &[PathBuf], out: &Path) -> String {
    let curves: Vec<&PathBuf> = files
        .iter()
        .filter(|f| {
            let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.starts_with("val_") && name.ends_with(".png")
        })
        .collect();
    if curves.is_empty() {
        return String::new();
    }
    let mut report = String::from(
        "## Training\n\nValidation metric against the step, per fine-tuning group: mean over \
         seeds, band one standard deviation over seeds (the table of how flat each curve ends, \
         and the timings: [training.md](training.md)).\n\n",
    );
    for f in curves {
        report += &format!("![{0}]({0})\n", rel(f, out));
    }
    report + "\n"
}

/// The calibrated gain against the field of view ([`super::fov`]), when two or more FT data
/// sets have both kernels.
fn fov_section(cx: &Ctx<'_>, files: &mut Vec<PathBuf>) -> Result<String> {
    let rows = super::fov::fov_gain(cx.study, cx.obs)?;
    let written = super::fov::write_fov_gain(&rows, cx.out)?;
    if written.is_empty() {
        return Ok(String::new());
    }
    files.extend(written);
    let others = cx
        .study
        .elapsed_seconds_of(|r| !cx.study.evaluates_on(r, &CLAIM_DATASETS));
    let mut md = format!(
        "## Gain against the field of view\n\nFT rows, calibrated − standard per seed, mean and \
         95% Student-t interval over seeds, against the camera's field of view \
         ([fov_gain.json](fov_gain.json)). Elapsed wall time of the runs outside the verdict's \
         data sets (the field-of-view series): {others:.0} s.\n\n| task | metric | FOV (deg) | \
         data set | n | mean | 95% CI |\n|---|---|---:|---|---:|---:|---|\n",
    );
    for r in &rows {
        md += &format!(
            "| {} | {} | {:.0} | {} | {} | {:+.4} | {} |\n",
            r.task,
            r.metric,
            r.fov_deg,
            r.dataset,
            r.n_seeds,
            r.mean,
            ci_cell(r.ci95)
        );
    }
    md += "\n![gain vs field of view](fov_gain.png)\n\n";
    Ok(md)
}

/// A table cell with a 95% interval over seeds, `[lo, hi]`, or why there is none.
fn ci_cell(c: Option<[f64; 2]>) -> String {
    c.map(|[lo, hi]| format!("[{lo:+.4}, {hi:+.4}]"))
        .unwrap_or_else(|| "needs >= 2 seeds".into())
}

/// Markdown embedding every PNG of `written` (paths relative to `out`) under `alt`, and the
/// blank line that closes the section.
fn embed_plots(written: &[PathBuf], alt: &str, out: &Path) -> String {
    let mut md = String::new();
    for f in written {
        if f.extension().is_some_and(|e| e == "png") {
            md += &format!("\n![{alt}]({})\n", rel(f, out));
        }
    }
    md + "\n"
}

/// The data-efficiency series and the methods beyond the paper's ([`super::questions`]), when
/// their runs exist.
fn questions_section(cx: &Ctx<'_>, files: &mut Vec<PathBuf>) -> Result<String> {
    let mut md = String::new();
    let eff = super::questions::data_efficiency(cx.study, cx.obs)?;
    let written = super::questions::write_data_efficiency(&eff, cx.out)?;
    if !written.is_empty() {
        md += "## Data efficiency

FT from the same baseline on a fraction of the training \
               views (drawn with the seed, nested across fractions; the same steps for every \
               fraction), calibrated − standard per seed, mean and 95% Student-t interval \
               ([data_efficiency.json](data_efficiency.json); claim C7 in the verdict).\n\n\
               | task | metric | fraction | views | n | standard | calibrated | difference | 95% \
               CI |\n|---|---|---:|---:|---:|---:|---:|---:|---|\n";
        for r in &eff {
            md += &format!(
                "| {} | {} | {} | {} | {} | {:.4} | {:.4} | {:+.4} | {} |\n",
                r.task,
                r.metric,
                r.fraction,
                r.train_images,
                r.n_seeds,
                r.standard,
                r.calibrated,
                r.diff_mean,
                ci_cell(r.ci95)
            );
        }
        md += &embed_plots(&written, "data efficiency", cx.out);
        files.extend(written);
    }
    let methods = super::questions::methods(cx.obs);
    let written = super::questions::write_methods(&methods, cx.out)?;
    if !written.is_empty() {
        md += "## Methods\n\nFT from the same baseline with each kind of convolution \
               (`camconv`: CAM-Convs' ray maps at the skip connections; `calibrated-learned`: \
               calibrated offsets plus a learned offset branch), mean and 95% interval over \
               seeds, and the paired difference to standard kernels \
               ([methods.json](methods.json)).\n\n| lens | task | metric | method | n | mean | \
               95% CI | − standard | 95% CI |\n|---|---|---|---|---:|---:|---|---:|---|\n";
        for r in &methods {
            md += &format!(
                "| {} | {} | {} | {} | {} | {:.4} | {} | {:+.4} | {} |\n",
                r.lens,
                r.task,
                r.metric,
                r.method,
                r.n_seeds,
                r.mean,
                ci_cell(r.ci95),
                r.diff_vs_standard.mean,
                ci_cell(r.diff_vs_standard.ci95)
            );
        }
        md += &embed_plots(&written, "methods", cx.out);
        files.extend(written);
    }
    Ok(md)
}

/// The runs, their times and configurations (`runs.md`).
fn runs_section(study: &Study, out: &Path) -> String {
    let mut report = String::from(
        "# Runs\n\n| seed | run | task | block | steps | training (s) | sweep wall (s) | \
               git | overrides |\n|---:|---|---|---|---:|---:|---:|---|---|\n",
    );
    for r in &study.runs {
        report += &format!(
            "| {} | [{}]({}) | {} | {} | {} | {} | {} | {} | {} |\n",
            r.seed,
            r.name,
            rel(&r.dir, out),
            r.task,
            r.block,
            r.steps.map(|s| s.to_string()).unwrap_or_default(),
            r.train_seconds
                .map(|s| format!("{s:.1}"))
                .unwrap_or_default(),
            r.sweep_seconds
                .map(|s| format!("{s:.1}"))
                .unwrap_or_default(),
            r.git.clone().unwrap_or_default(),
            r.overrides.join(" ")
        );
    }
    let (total, _) = study.wall_seconds();
    let elapsed = study.elapsed_seconds();
    report += &format!(
        "\nElapsed wall time of these runs: {elapsed:.1} s (the sum of their own wall times: \
         {total:.1} s; parallel runs overlap).\n\n## Configurations\n\n"
    );
    for r in &study.runs {
        report += &format!(
            "<details><summary>{} (seed {}, {})</summary>\n\n```toml\n{}\n```\n</details>\n\n",
            r.name,
            r.seed,
            r.profile
                .as_deref()
                .map(|p| format!("profile `{p}`"))
                .unwrap_or_else(|| "no profile".into()),
            r.text.trim_end()
        );
    }
    report
}
