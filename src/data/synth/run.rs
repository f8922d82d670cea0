//! The job runner of `synth`: each set's folder checked and its pending samples listed
//! ([`prepare_set`]), then every panorama loaded once and its views written ([`run_jobs`]).

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::config::{SetPlan, SynthPlan, ViewKind};
use crate::camera::{self, CameraModel};
use crate::data::format::{
    encode_sample, png_size, sample_path, Counts, Manifest, Split, Splits, DEPTH_SCALE, GENERATOR,
    GENERATOR_VERSION, MANIFEST, SAMPLE_DIRS,
};
use crate::data::panorama::Panorama;
use crate::data::source::PanoramaSource;
use crate::data::views::{RayGrid, Rectifier, View};
use crate::data::{CLASSES, UNKNOWN_PNG_LABEL};
use crate::error::{Error, Result};
use crate::io::write_bytes_atomic;

/// Sample id of view `view` of panorama `name`.
pub fn sample_id(name: &str, view: usize) -> String {
    format!("{name}_v{view}")
}

/// The rays of a set's camera (and the rectification mapping), computed once per set.
#[derive(Clone, Debug)]
pub struct SetRenderer {
    grid: RayGrid,
    rectifier: Option<Rectifier>,
}

impl SetRenderer {
    /// Precomputes the rays of `set` (the fisheye's for a rectified set).
    pub fn new(plan: &SynthPlan, set: &SetPlan) -> Result<Self> {
        Ok(match &set.fisheye {
            None => SetRenderer {
                grid: RayGrid::new(&set.camera, plan.supersample)?,
                rectifier: None,
            },
            Some(fish) => SetRenderer {
                grid: RayGrid::new(fish, plan.supersample)?,
                rectifier: Some(Rectifier::new(fish, &set.camera)?),
            },
        })
    }

    /// Renders view `view` of the panorama with key `key` (see [`PanoramaSource::key`]).
    pub fn render(&self, plan: &SynthPlan, pano: &Panorama, key: u64, view: usize) -> Result<View> {
        let o = plan.sampling.orientation(plan.seed, key, view as u64);
        let v = self.grid.render(pano, &o)?;
        match &self.rectifier {
            None => Ok(v),
            Some(r) => r.apply(&v),
        }
    }
}

/// What to do about a folder that is not a finished or resumable run of the same plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GenerateOptions {
    /// Overwrite a folder made by another generator version / seed / configuration, or a
    /// non-empty folder without a manifest.
    pub force: bool,
}

/// One set prepared for writing: its folder checked, its manifest built, the samples still to
/// write listed.
pub struct SetJob {
    /// The set.
    pub set: SetPlan,
    /// Its folder.
    pub dir: PathBuf,
    renderer: SetRenderer,
    camera_toml: String,
    manifest: Manifest,
    /// Per panorama index, the views still to write.
    todo: Vec<Vec<usize>>,
    total: usize,
    /// Whether finished samples are kept (false with `force` on a mismatching folder).
    resume: bool,
}

impl SetJob {
    /// Samples in the set.
    pub fn total(&self) -> usize {
        self.total
    }
    /// Samples still to write.
    pub fn pending(&self) -> usize {
        self.todo.iter().map(Vec::len).sum()
    }
    /// The manifest that will be written.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Makes the folder ready to receive samples: removes temporary files of an interrupted
    /// run (`io::write_atomic` names them `.NAME.tmp-PID`) and, when not resuming (`force`),
    /// sample files of ids no longer in the set; writes `camera.toml` and the manifest with
    /// `complete: false`. Nothing is written for a finished set with nothing to do.
    fn begin(&self) -> Result<()> {
        let dir = &self.dir;
        if self.resume && self.pending() == 0 && dir.join(MANIFEST).exists() {
            return Ok(());
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let ids: HashSet<&String> = self.manifest.splits.all().collect();
        for sub in SAMPLE_DIRS {
            let d = dir.join(sub);
            std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
            for entry in std::fs::read_dir(&d).map_err(|e| Error::io(&d, e))? {
                let entry = entry.map_err(|e| Error::io(&d, e))?;
                let name = entry.file_name().to_string_lossy().into_owned();
                let stale_tmp = name.starts_with('.') && name.contains(".tmp-");
                let stale_sample = !self.resume
                    && name
                        .strip_suffix(".png")
                        .is_some_and(|id| !ids.contains(&id.to_string()));
                if stale_tmp || stale_sample {
                    let p = entry.path();
                    std::fs::remove_file(&p).map_err(|e| Error::io(&p, e))?;
                }
            }
        }
        write_bytes_atomic(&dir.join("camera.toml"), self.camera_toml.as_bytes())?;
        write_bytes_atomic(&dir.join(MANIFEST), self.manifest.to_json().as_bytes())
    }
}

/// Checks the folder of `set` (see the module docs, "Safe") and lists the samples still to
/// write. Writes nothing: [`run_jobs`] does, once every set has been checked, so a refusal of
/// one set leaves the others untouched.
///
/// # Errors
/// A folder that is not ours to write (without `force`), unreadable files.
pub fn prepare_set(
    plan: &SynthPlan,
    set: &SetPlan,
    source: &dyn PanoramaSource,
    options: &GenerateOptions,
) -> Result<SetJob> {
    let dir = plan.set_dir(set);
    let (n, k) = (source.len(), plan.per_panorama);
    let manifest = new_manifest(plan, set, source);
    let resume = resumable(&dir, &manifest, options)?;
    let [width, height] = set.camera.size();
    let todo = pending_views(source, k, &dir, [width, height], resume);
    let description = format!(
        "{} rescaled to {}x{} (half-pixel convention) by calibconv synth{}",
        set.camera_path
            .file_name()
            .map_or("camera".into(), |f| f.to_string_lossy().into_owned()),
        width,
        height,
        if set.kind == ViewKind::Rectified {
            ", then rectified to this pinhole"
        } else {
            ""
        }
    );
    Ok(SetJob {
        set: set.clone(),
        renderer: SetRenderer::new(plan, set)?,
        camera_toml: camera::to_toml(&set.camera, &[], Some(&set.name), Some(&description)),
        dir,
        manifest,
        todo,
        total: n * k,
        resume,
    })
}

/// The manifest of `set` as this run will write it (`complete: false`): every sample id by
/// split, the counts and the settings compared on resume.
fn new_manifest(plan: &SynthPlan, set: &SetPlan, source: &dyn PanoramaSource) -> Manifest {
    let n = source.len();
    let k = plan.per_panorama;
    let mut splits = Splits::default();
    for i in 0..n {
        let ids = (0..k).map(|v| sample_id(&source.name(i), v));
        match source.split(i) {
            Split::Train => splits.train.extend(ids),
            Split::Val => splits.val.extend(ids),
            Split::Test => splits.test.extend(ids),
        }
    }
    let [width, height] = set.camera.size();
    Manifest {
        generator: GENERATOR.into(),
        generator_version: GENERATOR_VERSION,
        complete: false,
        name: set.name.clone(),
        kind: set.kind.as_str().into(),
        seed: plan.seed,
        camera: "camera.toml".into(),
        camera_source: set.camera_path.display().to_string(),
        panorama_source: source.describe(),
        width,
        height,
        depth_scale: DEPTH_SCALE,
        classes: CLASSES.iter().map(|s| s.to_string()).collect(),
        unknown_label: UNKNOWN_PNG_LABEL,
        counts: Counts {
            panoramas: n,
            views_per_panorama: k,
            samples: n * k,
            train: splits.train.len(),
            val: splits.val.len(),
            test: splits.test.len(),
        },
        splits,
        config: plan.manifest_config(set),
    }
}

/// Whether the folder `dir` holds a run of the same plan to resume (or nothing): `false` when
/// `force` overrides a mismatching manifest or a non-empty folder without one.
///
/// # Errors
/// Such a folder without `force`; unreadable files.
fn resumable(dir: &Path, manifest: &Manifest, options: &GenerateOptions) -> Result<bool> {
    let manifest_path = dir.join(MANIFEST);
    let mut resume = true;
    if manifest_path.exists() {
        let text =
            std::fs::read_to_string(&manifest_path).map_err(|e| Error::io(&manifest_path, e))?;
        let mismatch = match Manifest::parse(&text, &manifest_path) {
            Err(e) => Some(e.to_string()),
            Ok(old) => {
                let diffs: Vec<&str> = [
                    ("seed", old.seed != manifest.seed),
                    ("config", old.config != manifest.config),
                    ("splits", old.splits != manifest.splits),
                    ("name", old.name != manifest.name),
                ]
                .iter()
                .filter(|(_, d)| *d)
                .map(|(f, _)| *f)
                .collect();
                (!diffs.is_empty()).then(|| {
                    format!(
                        "{}: made with a different {} than this run",
                        manifest_path.display(),
                        diffs.join(", ")
                    )
                })
            }
        };
        if let Some(why) = mismatch {
            if !options.force {
                return Err(Error::data(
                    dir,
                    format!(
                        "refusing to overwrite: {why}; use --force to regenerate it, or \
                         another output folder"
                    ),
                ));
            }
            resume = false;
        }
    } else if dir.exists() {
        let non_empty = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .next()
            .is_some();
        if non_empty {
            if !options.force {
                return Err(Error::data(
                    dir,
                    "refusing to write into a non-empty folder without a manifest.json (not a \
                     data set made by calibconv synth); use --force, or another output folder",
                ));
            }
            resume = false;
        }
    }
    Ok(resume)
}

/// Per panorama, the views of which some file is missing or has the wrong size (every view
/// when not resuming).
fn pending_views(
    source: &dyn PanoramaSource,
    k: usize,
    dir: &Path,
    [width, height]: [usize; 2],
    resume: bool,
) -> Vec<Vec<usize>> {
    let preview = [3 * width, height];
    (0..source.len())
        .into_par_iter()
        .map(|i| {
            (0..k)
                .filter(|&v| {
                    let id = sample_id(&source.name(i), v);
                    !resume
                        || !SAMPLE_DIRS.iter().all(|sub| {
                            let want = if *sub == "previews" {
                                preview
                            } else {
                                [width, height]
                            };
                            png_size(&sample_path(dir, sub, &id)).ok() == Some(want)
                        })
                })
                .collect()
        })
        .collect()
}

/// What a run did.
#[derive(Clone, Debug, PartialEq)]
pub struct RunReport {
    /// Samples written, over all sets.
    pub written: usize,
    /// Panoramas loaded or rendered.
    pub panoramas: usize,
    /// Seconds spent.
    pub seconds: f64,
}

/// Writes the pending samples of every job (after [`SetJob`]'s preparation of each folder:
/// stale temporary files removed, `camera.toml` and an incomplete manifest written), loading
/// each panorama once for all sets, panoramas in parallel; calls `progress(1)` after each
/// sample; marks each manifest complete at the end.
pub fn run_jobs(
    plan: &SynthPlan,
    jobs: &[SetJob],
    source: &dyn PanoramaSource,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<RunReport> {
    let start = Instant::now();
    for job in jobs {
        job.begin()?;
    }
    let n = source.len();
    let written = AtomicUsize::new(0);
    let loaded = AtomicUsize::new(0);
    let pending: Vec<usize> = (0..n)
        .filter(|&i| jobs.iter().any(|j| !j.todo[i].is_empty()))
        .collect();
    pending.par_iter().try_for_each(|&i| -> Result<()> {
        let pano = source.load(i)?;
        loaded.fetch_add(1, Ordering::Relaxed);
        let name = source.name(i);
        for job in jobs {
            for &v in &job.todo[i] {
                let view = job.renderer.render(plan, &pano, source.key(i), v)?;
                let enc = encode_sample(&view, DEPTH_SCALE);
                let id = sample_id(&name, v);
                for (sub, bytes) in SAMPLE_DIRS.iter().zip(enc.files()) {
                    write_bytes_atomic(&sample_path(&job.dir, sub, &id), bytes)?;
                }
                written.fetch_add(1, Ordering::Relaxed);
                progress(1);
            }
        }
        Ok(())
    })?;
    for job in jobs {
        let mut m = job.manifest.clone();
        m.complete = true;
        write_bytes_atomic(&job.dir.join(MANIFEST), m.to_json().as_bytes())?;
    }
    Ok(RunReport {
        written: written.into_inner(),
        panoramas: loaded.into_inner(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Prepares and runs every set of `plan` without progress output (the library entry point;
/// the CLI does the same with progress bars).
pub fn synthesize(plan: &SynthPlan, options: &GenerateOptions) -> Result<RunReport> {
    let source = plan.open_source()?;
    let jobs = plan
        .sets
        .iter()
        .map(|s| prepare_set(plan, s, source.as_ref(), options))
        .collect::<Result<Vec<_>>>()?;
    run_jobs(plan, &jobs, source.as_ref(), &|_| {})
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::synth::config::tiny_plan;

    #[test]
    fn resume_rewrites_only_missing_samples_and_refuses_foreign_folders() {
        let tmp = tempfile::tempdir().unwrap();
        let plan = tiny_plan(tmp.path());
        let report = synthesize(&plan, &GenerateOptions::default()).unwrap();
        assert_eq!(report.written, 4 * 3 * 2);
        assert_eq!(report.panoramas, 3);
        let set = &plan.sets[0];
        let dir = plan.set_dir(set);
        let m = Manifest::read(&dir).unwrap();
        assert!(m.complete);
        // Delete one file: only that sample is redone, and only its panorama is rendered.
        let victim = sample_path(&dir, "labels", &m.splits.train[0]);
        let before = std::fs::read(&victim).unwrap();
        std::fs::remove_file(&victim).unwrap();
        let report = synthesize(&plan, &GenerateOptions::default()).unwrap();
        assert_eq!((report.written, report.panoramas), (1, 1));
        assert_eq!(std::fs::read(&victim).unwrap(), before);
        // Another seed is refused without --force...
        let mut other = plan.clone();
        other.seed += 1;
        let e = synthesize(&other, &GenerateOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("refusing") && e.contains("seed"), "{e}");
        assert_eq!(std::fs::read(&victim).unwrap(), before);
        // ...and regenerated with it.
        let report = synthesize(&other, &GenerateOptions { force: true }).unwrap();
        assert_eq!(report.written, 4 * 3 * 2);
        assert_ne!(std::fs::read(&victim).unwrap(), before);
        // A refusal of one set writes nothing into the others.
        let manifest = std::fs::read(dir.join(MANIFEST)).unwrap();
        let last = plan.set_dir(plan.sets.last().unwrap());
        std::fs::remove_dir_all(&last).unwrap();
        std::fs::create_dir_all(&last).unwrap();
        std::fs::write(last.join("notes.txt"), "mine").unwrap();
        let e = synthesize(&other, &GenerateOptions::default()).unwrap_err();
        assert!(e.to_string().contains("without a manifest"), "{e}");
        assert_eq!(std::fs::read(dir.join(MANIFEST)).unwrap(), manifest);
    }
}
