//! `calibconv synth`: write data sets of views rendered from panoramas (see
//! `calibconv::data::synth` for the configuration and the guarantees).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use std::time::Instant;

use rayon::prelude::*;

use calibconv::camera::CameraModel;
use calibconv::data::synth::{
    prepare_set, run_jobs, GenerateOptions, PanoramaSource, RawSet, RawSynthConfig, SetRenderer,
    SourceKind, SynthPlan, ViewKind,
};

/// Flags of `calibconv synth`; each one overrides the configuration.
#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Configuration file (TOML; default: the embedded data/synth.toml, four 128 px sets
    /// f195, f165, pers, rect-f165 from 40 procedural panoramas).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output root; each set is written to OUT/NAME.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed of scenes, orientations and splits.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Only this set of the configuration (repeatable).
    #[arg(long = "set", value_name = "NAME")]
    pub sets: Vec<String>,
    /// Number of panoramas (with --stanford: 0 = all, the default there).
    #[arg(long)]
    pub panoramas: Option<usize>,
    /// Panorama height in pixels (width = 2 x height); Stanford panoramas are box-filtered to
    /// it (2048 must be a multiple of it).
    #[arg(long)]
    pub pano_height: Option<usize>,
    /// Views per panorama and set.
    #[arg(long)]
    pub views_per_panorama: Option<usize>,
    /// Stored image width of every set (the camera is scaled to it).
    #[arg(long)]
    pub width: Option<usize>,
    /// Instead of the configuration's sets, one set of this kind: pers, fisheye or rectified
    /// (needs --camera).
    #[arg(long)]
    pub kind: Option<ViewKind>,
    /// Camera file of the --kind set.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// Folder name of the --kind set (default: the kind).
    #[arg(long)]
    pub name: Option<String>,
    /// Horizontal FOV of the pinhole of a rectified --kind set (default: the fisheye's focal).
    #[arg(long)]
    pub rectify_hfov_deg: Option<f64>,
    /// Render from a Stanford 2D-3D-S copy at ROOT (area_*/pano/{rgb,depth,semantic}) instead
    /// of procedural panoramas; fold 1 split (area 5 = test).
    #[arg(long, value_name = "ROOT")]
    pub stanford: Option<PathBuf>,
    /// The Stanford label list (default: ROOT/assets/semantic_labels.json).
    #[arg(long)]
    pub stanford_labels: Option<PathBuf>,
    /// Overwrite folders made by another generator version, seed or configuration (and
    /// non-empty folders without a manifest).
    #[arg(long)]
    pub force: bool,
    /// Print what would be written and exit.
    #[arg(long)]
    pub dry_run: bool,
    /// Only measure, writing nothing: load or render the panoramas (in parallel, as synth
    /// does) and print panoramas/s, then render views of each set from them and print views/s.
    #[arg(long)]
    pub bench: bool,
}

/// The configuration with the flags applied.
fn configure(args: &SynthArgs) -> Result<(RawSynthConfig, PathBuf)> {
    let (mut raw, path) = match &args.config {
        Some(p) => (
            RawSynthConfig::load(p)
                .with_context(|| format!("cannot use config {}", p.display()))?,
            p.clone(),
        ),
        None => (
            RawSynthConfig::default_config(),
            PathBuf::from("<embedded data/synth.toml>"),
        ),
    };
    if let Some(out) = &args.out {
        raw.out = out.clone();
    }
    if let Some(seed) = args.seed {
        raw.seed = seed;
    }
    if let Some(root) = &args.stanford {
        raw.panoramas.source = SourceKind::Stanford;
        raw.panoramas.stanford_root = Some(root.clone());
        // All panoramas unless --panoramas says otherwise.
        raw.panoramas.count = args.panoramas.unwrap_or(0);
    }
    if let Some(labels) = &args.stanford_labels {
        raw.panoramas.stanford_labels = Some(labels.clone());
    }
    if let Some(n) = args.panoramas {
        raw.panoramas.count = n;
    }
    if let Some(h) = args.pano_height {
        raw.panoramas.height = h;
    }
    if let Some(k) = args.views_per_panorama {
        raw.views.per_panorama = k;
    }
    match (&args.kind, &args.camera) {
        (Some(kind), Some(camera)) => {
            if !args.sets.is_empty() {
                bail!("--set selects sets of the configuration; it cannot be combined with --kind");
            }
            // The --kind set's camera is the user's file: read it from disk, even where its
            // path is one the embedded default embeds.
            raw.embedded_cameras = &[];
            raw.sets = vec![RawSet {
                name: args.name.clone().unwrap_or(kind.as_str().to_string()),
                kind: *kind,
                camera: camera.clone(),
                width: args
                    .width
                    .unwrap_or(raw.sets.first().map_or(128, |s| s.width)),
                rectify_hfov_deg: args.rectify_hfov_deg,
            }];
        }
        (Some(_), None) => bail!("--kind needs --camera"),
        (None, Some(_)) => bail!("--camera needs --kind (pers, fisheye or rectified)"),
        (None, None) => {
            if args.name.is_some() || args.rectify_hfov_deg.is_some() {
                bail!("--name and --rectify-hfov-deg describe a --kind set");
            }
            if !args.sets.is_empty() {
                let known: Vec<&str> = raw.sets.iter().map(|s| s.name.as_str()).collect();
                for want in &args.sets {
                    if !known.contains(&want.as_str()) {
                        bail!(
                            "--set {want}: no such set in {} (it has {})",
                            path.display(),
                            known.join(", ")
                        );
                    }
                }
                raw.sets.retain(|s| args.sets.contains(&s.name));
            }
            if let Some(w) = args.width {
                for s in raw.sets.iter_mut() {
                    s.width = w;
                }
            }
        }
    }
    Ok((raw, path))
}

pub fn run(args: SynthArgs) -> Result<()> {
    let (raw, path) = configure(&args)?;
    let plan = raw.resolve(&path)?;
    let source = plan.open_source()?;
    if args.bench {
        return bench(&plan, source.as_ref());
    }
    let options = GenerateOptions { force: args.force };
    let mut jobs = Vec::new();
    for set in &plan.sets {
        let dir = plan.set_dir(set);
        let [w, h] = set.camera.size();
        if args.dry_run {
            println!(
                "{}: {} {}x{} from {}, {} panoramas x {} views -> {}",
                set.name,
                set.kind.as_str(),
                w,
                h,
                set.camera_path.display(),
                source.len(),
                plan.per_panorama,
                dir.display()
            );
            continue;
        }
        let job = prepare_set(&plan, set, source.as_ref(), &options)
            .with_context(|| format!("cannot write set `{}`", set.name))?;
        println!(
            "{}: {} {}x{} ({}), {} samples, {} to write -> {}",
            set.name,
            set.kind.as_str(),
            w,
            h,
            set.camera_path.display(),
            job.total(),
            job.pending(),
            dir.display()
        );
        jobs.push(job);
    }
    if args.dry_run {
        return Ok(());
    }
    let pending: usize = jobs.iter().map(|j| j.pending()).sum();
    let bar = ProgressBar::new(pending as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} views ({per_sec}, eta {eta})",
        )
        .expect("valid template"),
    );
    let report = run_jobs(&plan, &jobs, source.as_ref(), &|n| bar.inc(n))?;
    bar.finish_and_clear();
    if report.written == 0 {
        println!("nothing to do: every sample was already complete");
    } else {
        println!(
            "wrote {} views from {} panoramas ({}) in {:.1} s: {:.2} panoramas/s, {:.1} views/s",
            report.written,
            report.panoramas,
            source.describe(),
            report.seconds,
            report.panoramas as f64 / report.seconds,
            report.written as f64 / report.seconds
        );
    }
    Ok(())
}

/// `--bench`: panoramas/s, then views/s per set, nothing written.
fn bench(plan: &SynthPlan, source: &dyn PanoramaSource) -> Result<()> {
    let n = source.len();
    let start = Instant::now();
    let panos = (0..n)
        .into_par_iter()
        .map(|i| source.load(i))
        .collect::<calibconv::Result<Vec<_>>>()?;
    let secs = start.elapsed().as_secs_f64();
    let (w, h) = (panos[0].width, panos[0].height);
    println!(
        "{n} panoramas {w}x{h} ({}) in {secs:.2} s: {:.2} panoramas/s ({} threads)",
        source.describe(),
        n as f64 / secs,
        rayon::current_num_threads()
    );
    for set in &plan.sets {
        let renderer = SetRenderer::new(plan, set)?;
        let views = n * plan.per_panorama;
        let start = Instant::now();
        for (i, pano) in panos.iter().enumerate() {
            for v in 0..plan.per_panorama {
                renderer.render(plan, pano, source.key(i), v)?;
            }
        }
        let secs = start.elapsed().as_secs_f64();
        let [cw, ch] = set.camera.size();
        println!(
            "{}: {views} {} views {cw}x{ch} (supersample {}) in {secs:.2} s: {:.1} views/s",
            set.name,
            set.kind.as_str(),
            plan.supersample,
            views as f64 / secs
        );
    }
    Ok(())
}
