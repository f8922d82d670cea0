//! The report of a sweep's output folder (`calibconv report RESULTS`): the paper's tables,
//! radial plots, qualitative grids and `REPORT.md`, read from the run directories that
//! training and evaluation wrote (see [`crate::experiment::run`]'s layout).
//!
//! Runs are grouped by task (`table_depth`, `table_seg`) and block: **BL** (no `model.init`)
//! and **FT** (with one). An evaluation named `SET-KERNEL` (`f195-calibrated`,
//! `f165-rectified`) is the row *data set* `SET`, *kernel* `KERNEL`; other names are rows of
//! their own (data set = the name, kernel = the evaluation's kernel). The best value of each
//! metric among the rows of one block and data set (one calibration) is bold.
//!
//! Radial plots (paper Figs. 3 and 5) show, per task, calibration and metric, the per-image
//! mean of the metric in rings around the principal point (`radial.csv`: `M_mean`, `M_std`
//! over the images), one standard deviation as a band; standard kernels red, calibrated blue,
//! rectified green. Distances are network-input pixels; the rectified images are another
//! (pinhole) projection, so their radius means another viewing angle.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use image::RgbImage;

use super::plots::{
    line_band_plot, Curve, PlotSpec, CALIBRATED_BLUE, RECTIFIED_GREEN, STANDARD_RED,
};
use crate::error::{Error, Result};
use crate::eval::metrics::ALL_METRICS;
use crate::io::{write_bytes_atomic, write_png_atomic};

/// Metric columns of each task's table, in order.
pub const DEPTH_COLUMNS: [&str; 7] = [
    "mre", "mae", "rmse", "rmse_log", "delta1", "delta2", "delta3",
];
/// Metric columns of the segmentation table.
pub const SEG_COLUMNS: [&str; 3] = ["miou", "macc", "pixel_acc"];
/// Metrics with radial plots, per task.
pub const DEPTH_RADIAL: [&str; 2] = ["rmse", "delta1"];
pub const SEG_RADIAL: [&str; 2] = ["miou", "macc"];

const KERNELS: [&str; 3] = ["standard", "calibrated", "rectified"];

/// One evaluation of one run.
#[derive(Clone, Debug)]
pub struct Row {
    pub run: String,
    /// `depth` or `segmentation`.
    pub task: String,
    /// `BL` or `FT`.
    pub block: String,
    pub dataset: String,
    pub kernel: String,
    pub evaluation: String,
    pub metrics: BTreeMap<String, f64>,
    /// `RUN/eval/NAME`.
    pub dir: PathBuf,
}

/// One run directory.
#[derive(Clone, Debug)]
pub struct RunInfo {
    pub name: String,
    pub dir: PathBuf,
    pub task: String,
    pub block: String,
    /// The experiment text it ran with (`experiment.toml`).
    pub text: String,
    /// Training wall time and steps (`summary.json`), sweep wall time (`sweep.json`).
    pub train_seconds: Option<f64>,
    pub steps: Option<u64>,
    pub sweep_seconds: Option<f64>,
    pub git: Option<String>,
    pub overrides: Vec<String>,
    pub profile: Option<String>,
}

fn read_json(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// The data set and kernel labels of an evaluation.
fn labels(name: &str, kernel: &str) -> (String, String) {
    match name.rsplit_once('-') {
        Some((set, k)) if KERNELS.contains(&k) => (set.to_uppercase(), k.to_string()),
        _ => (name.to_string(), kernel.to_string()),
    }
}

fn data_order(set: &str) -> (usize, String) {
    let i = ["PERS", "F195", "F165"]
        .iter()
        .position(|s| *s == set)
        .unwrap_or(9);
    (i, set.to_string())
}

fn kernel_order(k: &str) -> usize {
    KERNELS.iter().position(|s| *s == k).unwrap_or(9)
}

/// Reads every run directory of `results` (folders with `experiment.toml`) and their
/// evaluations.
pub fn collect(results: &Path) -> Result<(Vec<RunInfo>, Vec<Row>)> {
    let mut runs = Vec::new();
    let mut rows = Vec::new();
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(results)
        .map_err(|e| Error::io(results, e))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("experiment.toml").is_file())
        .collect();
    dirs.sort();
    for dir in dirs {
        let text = std::fs::read_to_string(dir.join("experiment.toml"))
            .map_err(|e| Error::io(dir.join("experiment.toml"), e))?;
        let table: toml::Table = toml::from_str(&text).map_err(|e| Error::Toml {
            path: dir.join("experiment.toml"),
            message: e.to_string(),
        })?;
        let name = table
            .get("name")
            .and_then(|v| v.as_str())
            .unwrap_or_default()
            .to_string();
        let task = table
            .get("task")
            .and_then(|v| v.as_str())
            .unwrap_or("depth")
            .to_string();
        let ft = table.get("model").and_then(|m| m.get("init")).is_some();
        let block = if ft { "FT" } else { "BL" }.to_string();
        let summary = read_json(&dir.join("summary.json"));
        let sweep = read_json(&dir.join("sweep.json"));
        let run_json = read_json(&dir.join("run.json"));
        runs.push(RunInfo {
            name: name.clone(),
            dir: dir.clone(),
            task: task.clone(),
            block: block.clone(),
            text: text.clone(),
            train_seconds: summary.as_ref().and_then(|s| s["seconds"].as_f64()),
            steps: summary.as_ref().and_then(|s| s["steps"].as_u64()),
            sweep_seconds: sweep.as_ref().and_then(|s| s["seconds"].as_f64()),
            git: run_json.as_ref().and_then(|r| {
                r["invocations"]
                    .as_array()
                    .and_then(|a| a.last())
                    .and_then(|l| l["git"].as_str())
                    .map(String::from)
            }),
            overrides: sweep
                .as_ref()
                .and_then(|s| s["overrides"].as_array().cloned())
                .unwrap_or_default()
                .iter()
                .filter_map(|v| v.as_str().map(String::from))
                .collect(),
            profile: sweep
                .as_ref()
                .and_then(|s| s["profile"].as_str().map(String::from)),
        });
        let mut evals: Vec<PathBuf> = std::fs::read_dir(dir.join("eval"))
            .map(|it| it.flatten().map(|e| e.path()).collect())
            .unwrap_or_default();
        evals.sort();
        for e in evals {
            let Some(doc) = read_json(&e.join("metrics.json")) else {
                continue;
            };
            let evaluation = doc["evaluation"]
                .as_str()
                .map(String::from)
                .unwrap_or_else(|| e.file_name().unwrap().to_string_lossy().into_owned());
            let kernel = doc["kernel"].as_str().unwrap_or("").to_string();
            let (dataset, kernel) = labels(&evaluation, &kernel);
            let metrics = doc["metrics"]
                .as_object()
                .map(|m| {
                    m.iter()
                        .filter_map(|(k, v)| v.as_f64().map(|x| (k.clone(), x)))
                        .collect()
                })
                .unwrap_or_default();
            rows.push(Row {
                run: name.clone(),
                task: task.clone(),
                block: block.clone(),
                dataset,
                kernel,
                evaluation,
                metrics,
                dir: e,
            });
        }
    }
    rows.sort_by(|a, b| {
        (
            &a.task,
            &a.block,
            data_order(&a.dataset),
            kernel_order(&a.kernel),
            &a.run,
        )
            .cmp(&(
                &b.task,
                &b.block,
                data_order(&b.dataset),
                kernel_order(&b.kernel),
                &b.run,
            ))
    });
    Ok((runs, rows))
}

fn higher_is_better(metric: &str) -> bool {
    ALL_METRICS
        .iter()
        .find(|m| m.name() == metric)
        .is_some_and(|m| m.higher_is_better())
}

/// The Markdown and CSV tables of `rows` (one task) with `columns`.
pub fn table(rows: &[&Row], columns: &[&str]) -> (String, String) {
    let arrow = |c: &str| if higher_is_better(c) { "↑" } else { "↓" };
    let mut md = format!(
        "| Training | Data set | Kernel | {} |\n|---|---|---|{}\n",
        columns
            .iter()
            .map(|c| format!("{c} {}", arrow(c)))
            .collect::<Vec<_>>()
            .join(" | "),
        "---:|".repeat(columns.len())
    );
    let mut csv = format!(
        "block,run,evaluation,dataset,kernel,{}\n",
        columns.join(",")
    );
    for r in rows {
        let peers: Vec<&&Row> = rows
            .iter()
            .filter(|o| o.block == r.block && o.dataset == r.dataset)
            .collect();
        let cells: Vec<String> = columns
            .iter()
            .map(|c| match r.metrics.get(*c) {
                None => "–".to_string(),
                Some(v) => {
                    let best = peers.len() > 1
                        && peers.iter().all(|o| {
                            let w = o.metrics.get(*c).copied().unwrap_or(f64::NAN);
                            !w.is_finite()
                                || if higher_is_better(c) {
                                    *v >= w
                                } else {
                                    *v <= w
                                }
                        });
                    if best {
                        format!("**{v:.4}**")
                    } else {
                        format!("{v:.4}")
                    }
                }
            })
            .collect();
        let block = if r.block == "BL" { "BL (Pers)" } else { "FT" };
        md += &format!(
            "| {block} | {} | {} | {} |\n",
            r.dataset,
            r.kernel,
            cells.join(" | ")
        );
        csv += &format!(
            "{},{},{},{},{},{}\n",
            r.block,
            r.run,
            r.evaluation,
            r.dataset,
            r.kernel,
            columns
                .iter()
                .map(|c| r
                    .metrics
                    .get(*c)
                    .map(|v| format!("{v}"))
                    .unwrap_or_default())
                .collect::<Vec<_>>()
                .join(",")
        );
    }
    (md, csv)
}

/// `radial.csv` of an evaluation: bin centres, and the mean and std of `metric` per bin.
pub fn read_radial(dir: &Path, metric: &str) -> Result<Curve> {
    let path = dir.join("radial.csv");
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = |name: &str| {
        header.iter().position(|h| *h == name).ok_or_else(|| {
            Error::InvalidArgument(format!("{}: no column `{name}`", path.display()))
        })
    };
    let (lo, hi) = (col("r_lo")?, col("r_hi")?);
    let (m, s) = (
        col(&format!("{metric}_mean"))?,
        col(&format!("{metric}_std"))?,
    );
    let mut curve = Curve {
        label: String::new(),
        colour: [0, 0, 0],
        x: vec![],
        mean: vec![],
        std: vec![],
    };
    for line in lines {
        let f: Vec<f64> = line
            .split(',')
            .map(|v| v.parse().unwrap_or(f64::NAN))
            .collect();
        if f.len() < header.len() {
            continue;
        }
        curve.x.push((f[lo] + f[hi]) / 2.0);
        curve.mean.push(f[m]);
        curve.std.push(f[s]);
    }
    Ok(curve)
}

fn colour(kernel: &str) -> [u8; 3] {
    match kernel {
        "calibrated" => CALIBRATED_BLUE,
        "rectified" => RECTIFIED_GREEN,
        _ => STANDARD_RED,
    }
}

fn task_short(task: &str) -> &'static str {
    if task == "segmentation" {
        "seg"
    } else {
        "depth"
    }
}

/// Radial plots of one task: per block with more than one kernel on a fisheye data set, per
/// data set and metric, `radial_TASK_BLOCK_SET_METRIC.png` in `out`. Returns the files.
pub fn radial_plots(rows: &[&Row], metrics: &[&str], out: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let mut groups: BTreeMap<(String, String, String), Vec<&Row>> = BTreeMap::new();
    for r in rows {
        if r.dataset != "PERS" {
            groups
                .entry((r.task.clone(), r.block.clone(), r.dataset.clone()))
                .or_default()
                .push(r);
        }
    }
    for ((task, block, set), group) in groups {
        if group.len() < 2 {
            continue;
        }
        for metric in metrics {
            let mut curves = Vec::new();
            for r in &group {
                if let Ok(mut c) = read_radial(&r.dir, metric) {
                    c.label = r.kernel.clone();
                    c.colour = colour(&r.kernel);
                    curves.push(c);
                }
            }
            if curves.is_empty() {
                continue;
            }
            let file = out.join(format!(
                "radial_{}_{}_{}_{metric}.png",
                task_short(&task),
                block.to_lowercase(),
                set.to_lowercase()
            ));
            let spec = PlotSpec {
                title: format!("{set}, {block}: {metric} vs distance to the principal point"),
                x_label: "distance to the principal point (input px)".into(),
                y_label: format!("{metric} (mean ± 1 std over images)"),
                size: [800, 500],
            };
            line_band_plot(&file, &spec, &curves)?;
            files.push(file);
        }
    }
    Ok(files)
}

fn load_png(path: &Path) -> Option<RgbImage> {
    image::open(path).ok().map(|i| i.to_rgb8())
}

fn save_png(path: &Path, img: &RgbImage) -> Result<()> {
    write_png_atomic(path, img)
}

/// Tile `i` of a prediction panel of `n` tiles (tiles separated by 2-pixel gaps, see
/// [`crate::eval::visual::hstack`]).
fn tile(panel: &RgbImage, n: u32, i: u32) -> RgbImage {
    const GAP: u32 = 2;
    let w = (panel.width() + GAP).saturating_sub(GAP * n) / n;
    image::imageops::crop_imm(panel, i * (w + GAP), 0, w, panel.height()).to_image()
}

/// Qualitative grids (RGB | standard | calibrated | ground truth) for each task, block and
/// fisheye data set with both kernels, from the evaluations' prediction panels;
/// `grid_TASK_BLOCK_SET.png`. Returns the files.
pub fn qualitative_grids(rows: &[&Row], out: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let mut groups: BTreeMap<(String, String, String), BTreeMap<String, &Row>> = BTreeMap::new();
    for r in rows {
        groups
            .entry((r.task.clone(), r.block.clone(), r.dataset.clone()))
            .or_default()
            .insert(r.kernel.clone(), r);
    }
    for ((task, block, set), by_kernel) in groups {
        let (Some(std_row), Some(cal_row)) =
            (by_kernel.get("standard"), by_kernel.get("calibrated"))
        else {
            continue;
        };
        // Depth panels: RGB | GT | prediction | error; segmentation: RGB | GT | prediction.
        let n = if task == "segmentation" { 3 } else { 4 };
        let mut ids: Vec<PathBuf> = std::fs::read_dir(std_row.dir.join("predictions"))
            .map(|it| it.flatten().map(|e| e.path()).collect())
            .unwrap_or_default();
        ids.sort();
        let mut lines = Vec::new();
        for p in ids.iter().take(4) {
            let Some(name) = p.file_name() else { continue };
            let (Some(a), Some(b)) = (
                load_png(p),
                load_png(&cal_row.dir.join("predictions").join(name)),
            ) else {
                continue;
            };
            lines.push(crate::eval::visual::hstack(&[
                tile(&a, n, 0),
                tile(&a, n, 2),
                tile(&b, n, 2),
                tile(&a, n, 1),
            ]));
        }
        if lines.is_empty() {
            continue;
        }
        let w = lines.iter().map(|l| l.width()).max().unwrap_or(0);
        let h: u32 = lines.iter().map(|l| l.height() + 2).sum();
        let mut grid = RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
        let mut y = 0;
        for l in &lines {
            image::imageops::replace(&mut grid, l, 0, y as i64);
            y += l.height() + 2;
        }
        let file = out.join(format!(
            "grid_{}_{}_{}.png",
            task_short(&task),
            block.to_lowercase(),
            set.to_lowercase()
        ));
        save_png(&file, &grid)?;
        files.push(file);
    }
    Ok(files)
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

/// Writes the tables, radial plots, grids and `REPORT.md` of `results` into `out`; returns the
/// files written.
pub fn write_report(results: &Path, out: &Path) -> Result<Vec<PathBuf>> {
    let (runs, rows) = collect(results)?;
    if runs.is_empty() {
        return Err(Error::InvalidArgument(format!(
            "{}: no run directories (folders with experiment.toml); run a sweep first",
            results.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let mut files = Vec::new();
    let mut report = format!(
        "# Report: {}\n\nRuns: {}. Generated by `calibconv report` from the run directories \
         (metrics: `RUN/eval/NAME/metrics.json`; the best value per block and calibration in \
         bold; ↓ lower is better, ↑ higher is better).\n\n",
        results.display(),
        runs.len()
    );
    for (task, short, columns, radial, title) in [
        (
            "depth",
            "depth",
            &DEPTH_COLUMNS[..],
            &DEPTH_RADIAL[..],
            "Table 1: depth",
        ),
        (
            "segmentation",
            "seg",
            &SEG_COLUMNS[..],
            &SEG_RADIAL[..],
            "Table 2: semantic segmentation",
        ),
    ] {
        let task_rows: Vec<&Row> = rows.iter().filter(|r| r.task == task).collect();
        if task_rows.is_empty() {
            continue;
        }
        let (md, csv) = table(&task_rows, columns);
        let md_file = out.join(format!("table_{short}.md"));
        let csv_file = out.join(format!("table_{short}.csv"));
        write_bytes_atomic(&md_file, format!("## {title}\n\n{md}").as_bytes())?;
        write_bytes_atomic(&csv_file, csv.as_bytes())?;
        files.extend([md_file.clone(), csv_file.clone()]);
        report += &format!(
            "## {title}\n\n{md}\n([{}]({}), [{}]({}))\n\n",
            rel(&md_file, out),
            rel(&md_file, out),
            rel(&csv_file, out),
            rel(&csv_file, out)
        );
        let plots = radial_plots(&task_rows, radial, out)?;
        if !plots.is_empty() {
            report += "### Radial plots\n\nMetric vs distance to the principal point (mean ± 1 \
                       std over the test images); standard kernels red, calibrated blue, \
                       rectified green (rectified images are a pinhole projection: the same \
                       radius is another viewing angle).\n\n";
            for p in &plots {
                report += &format!("![{0}]({0})\n", rel(p, out));
            }
            report += "\n";
        }
        files.extend(plots);
        let grids = qualitative_grids(&task_rows, out)?;
        if !grids.is_empty() {
            report += &format!(
                "### Qualitative results\n\nColumns: RGB | standard | calibrated | ground truth \
                 (first test images).{}\n\n",
                if task == "depth" {
                    " Depth colour map: near dark blue to far yellow, per image over [0, max \
                     ground truth]; invalid pixels black."
                } else {
                    " Classes: the fixed palette below; unknown / invalid black."
                }
            );
            for g in &grids {
                report += &format!("![{0}]({0})\n", rel(g, out));
            }
            report += "\n";
            if task == "segmentation" {
                report += &legend_md();
                report += "\n";
            }
        }
        files.extend(grids);
    }
    if out.join("pointcloud_top.png").is_file() {
        let about = std::fs::read_to_string(out.join("pointcloud.txt")).unwrap_or_default();
        report += &format!(
            "## Point cloud\n\nPredicted (blue) and true (grey) depth of one test image \
             back-projected with the camera model (depth = distance along the ray), seen from \
             above, camera at the black dot ({about}); [predicted](pointcloud_pred.ply), \
             [true](pointcloud_true.ply) as PLY.\n\n![top view](pointcloud_top.png)\n\n"
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
    report += "## Runs\n\n| run | task | block | steps | training (s) | sweep wall (s) | git | \
               overrides |\n|---|---|---|---:|---:|---:|---|---|\n";
    for r in &runs {
        report += &format!(
            "| [{}]({}) | {} | {} | {} | {} | {} | {} | {} |\n",
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
    let total: f64 = runs.iter().filter_map(|r| r.sweep_seconds).sum();
    report +=
        &format!("\nTotal sweep wall time of these runs: {total:.1} s.\n\n## Configurations\n\n");
    for r in &runs {
        report += &format!(
            "<details><summary>{} ({})</summary>\n\n```toml\n{}\n```\n</details>\n\n",
            r.name,
            r.profile
                .as_deref()
                .map(|p| format!("profile `{p}`"))
                .unwrap_or_else(|| "no profile".into()),
            r.text.trim_end()
        );
    }
    let report_file = out.join("REPORT.md");
    write_bytes_atomic(&report_file, report.as_bytes())?;
    files.push(report_file);
    Ok(files)
}
