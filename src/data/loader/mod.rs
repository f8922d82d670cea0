//! A data set folder (written by `calibconv synth`) served as [`Batch`]es: the
//! [`BatchSource`] the trainer uses.
//!
//! # What a batch holds
//!
//! Shapes, dtypes and units are the contract of [`crate::data`]; in addition:
//! - the network input `[H, W]` is the stored size, or a size at least as large
//!   ([`InputSize`]); the stored image sits in the top-left corner and the **padding** on the
//!   right and bottom is zeros with `mask` false and labels [`IGNORE_LABEL`], exactly the
//!   [`InputFrame`] padding `[W - W_stored, H - H_stored]` the calibrated offsets expect
//!   ([`Dataset::input_frame`]); nothing is ever resized (render at the size you need instead:
//!   `synth --width`, which re-samples the panorama rather than an image);
//! - `labels` is [`IGNORE_LABEL`] where the label PNG says unknown (255, which includes
//!   everything outside a fisheye's image circle) and on padding; a pixel whose *depth* alone
//!   is missing keeps its class (so glass, often without depth, still trains segmentation) but
//!   has `mask` false, which is what depth losses use.
//!
//! # Order and parallelism
//!
//! The order of epoch `e` is a Fisher-Yates shuffle seeded by `(seed, e)` (or the manifest
//! order without shuffling), so a resumed run sees the same batches. A background thread
//! assembles batches ahead of the consumer (`prefetch` of them), decoding the samples of a
//! batch in parallel on rayon's pool; augmentation randomness is keyed by
//! `(seed, epoch, sample)`, so batches do not depend on timing or thread count.
//!
//! # Augmentations (only those that keep the calibration valid)
//!
//! The calibrated kernels are computed from the camera file, so an augmentation may change
//! pixels but not which ray each pixel sees:
//! - **photometric jitter** (brightness, contrast, saturation) never moves a pixel: always
//!   allowed. Pixels outside the image stay black;
//! - **horizontal flip** maps pixel column `u` to `W - 1 - u`, i.e. a camera with principal
//!   point `cx' = W - 1 - cx` and otherwise the same (Kannala-Brandt and pinhole models are
//!   mirror-symmetric about the vertical line through `cx`). It is allowed only when
//!   `|cx - (W - 1) / 2| <= `[`FLIP_MAX_PP_OFFSET_PX`], so the flipped camera differs from the
//!   file by at most twice that. The shipped 1080-wide cameras have `cx = 540 = (W - 1) / 2 +
//!   0.5`, so a flip is refused at full resolution and allowed from about half resolution on
//!   (at width 128, cx is 0.06 px off centre);
//! - **not allowed**: vertical flips and rotations (gravity would point up: a fisheye's
//!   distortion is symmetric but the scene statistics are not, and the paper's orientations
//!   keep the camera roughly level), crops, scaling and translations (they move the principal
//!   point or change the focal length, so the calibration would no longer describe the image).

use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;

use rayon::prelude::*;
use tch::Tensor;

use crate::camera::{self, Camera, CameraModel, PixelConvention};
use crate::data::format::{
    read_depth, read_labels, read_mask, read_rgb, sample_path, Manifest, Split,
};
use crate::data::rng::{tag, Rng};
use crate::data::views::image_region;
use crate::data::{Batch, BatchSource, IGNORE_LABEL, NUM_CLASSES};
use crate::error::{Error, Result};
use crate::kernel::InputFrame;

/// Largest distance of the principal point from the image centre `(W - 1) / 2`, in pixels, for
/// which a horizontal flip is allowed (the flip moves the principal point by twice this).
pub const FLIP_MAX_PP_OFFSET_PX: f64 = 0.25;

/// The network input size.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum InputSize {
    /// The stored image size (no padding).
    #[default]
    Stored,
    /// Exactly `[H, W]`, at least the stored size; padded right / bottom.
    Exact([usize; 2]),
    /// The stored size rounded up to a multiple of `m` in each direction (a U-Net of depth d
    /// needs `m = 2^d`); padded right / bottom.
    Multiple(usize),
}

/// Photometric jitter: each factor is drawn uniformly in `[1 - x, 1 + x]` per sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColorJitter {
    /// `v' = v b`.
    pub brightness: f32,
    /// `v' = (v - mean) c + mean`, `mean` the sample's mean grey inside the image.
    pub contrast: f32,
    /// `v' = grey + (v - grey) s`, `grey = 0.299 r + 0.587 g + 0.114 b`.
    pub saturation: f32,
}

impl Default for ColorJitter {
    fn default() -> Self {
        ColorJitter {
            brightness: 0.2,
            contrast: 0.2,
            saturation: 0.2,
        }
    }
}

/// Augmentations (see the module docs for why only these).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Augment {
    /// Flip horizontally with probability 1/2 (needs a centred principal point).
    pub hflip: bool,
    /// Photometric jitter, if any.
    pub jitter: Option<ColorJitter>,
}

/// How a [`Dataset`] serves batches.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoaderConfig {
    /// Samples per batch.
    pub batch_size: usize,
    /// Seeds the shuffle and the augmentations.
    pub seed: u64,
    /// Shuffle every epoch (otherwise the manifest order).
    pub shuffle: bool,
    /// Drop a last, incomplete batch.
    pub drop_last: bool,
    /// The network input size.
    pub input: InputSize,
    /// Augmentations.
    pub augment: Augment,
    /// Batches assembled ahead of the consumer (at least 1).
    pub prefetch: usize,
}

impl Default for LoaderConfig {
    fn default() -> Self {
        LoaderConfig {
            batch_size: 8,
            seed: 0,
            shuffle: true,
            drop_last: false,
            input: InputSize::Stored,
            augment: Augment::default(),
            prefetch: 2,
        }
    }
}

/// One stored sample, decoded (row-major, stored size).
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// The sample id.
    pub id: String,
    /// 8-bit RGB.
    pub rgb: Vec<[u8; 3]>,
    /// Metres, 0 = missing.
    pub depth: Vec<f32>,
    /// Class ids or `UNKNOWN_PNG_LABEL`.
    pub labels: Vec<u8>,
    /// Valid pixels.
    pub mask: Vec<bool>,
}

#[derive(Clone)]
struct Inner {
    root: PathBuf,
    split: Split,
    manifest: Manifest,
    camera: Camera,
    ids: Vec<String>,
    config: LoaderConfig,
    /// `[W, H]` stored.
    stored: [usize; 2],
    /// `[H, W]` network input.
    input: [usize; 2],
    /// Pixels inside the image (fisheye circle), stored size.
    inside: Vec<bool>,
}

/// How many of `n` samples a training-set `fraction` keeps ([`Dataset::keep_fraction`]):
/// `round(n * fraction)`, at least one.
pub fn fraction_len(n: usize, fraction: f64) -> usize {
    ((n as f64 * fraction).round() as usize).clamp(1, n.max(1))
}

/// A data set folder and one of its splits, served as batches (see the module docs).
#[derive(Clone)]
pub struct Dataset {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Dataset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dataset")
            .field("root", &self.inner.root)
            .field("split", &self.inner.split)
            .field("samples", &self.inner.ids.len())
            .field("input", &self.inner.input)
            .finish()
    }
}

impl Dataset {
    /// Opens `root` (a folder with `manifest.json`) for `split`.
    ///
    /// # Errors
    /// A missing or foreign manifest (another generator or generator version), an incomplete
    /// set, a camera file that disagrees with the manifest's size, a sample file listed but
    /// missing, an input size smaller than the images, a horizontal flip with an off-centre
    /// principal point, a zero batch size.
    pub fn open(root: &Path, split: Split, config: LoaderConfig) -> Result<Dataset> {
        let manifest = Manifest::read(root)?;
        manifest.check_complete(root)?;
        let camera_path = root.join(&manifest.camera);
        let camera = camera::load(&camera_path)?;
        let [w, h] = camera.size();
        if [w, h] != [manifest.width, manifest.height] {
            return Err(Error::data(
                &camera_path,
                format!(
                    "camera is {w}x{h}, {} says the images are {}x{}",
                    root.join("manifest.json").display(),
                    manifest.width,
                    manifest.height
                ),
            ));
        }
        if config.batch_size == 0 {
            return Err(Error::InvalidArgument("batch_size must be > 0".into()));
        }
        let input = input_size(config.input, [h, w])?;
        if config.augment.hflip {
            check_flippable(&camera, &camera_path)?;
        }
        let ids = manifest.splits.get(split).to_vec();
        check_samples(root, split, &ids)?;
        let inside = image_region(&camera);
        Ok(Dataset {
            inner: Arc::new(Inner {
                root: root.to_path_buf(),
                split,
                manifest,
                camera,
                ids,
                config: LoaderConfig {
                    prefetch: config.prefetch.max(1),
                    ..config
                },
                stored: [w, h],
                input,
                inside,
            }),
        })
    }

    /// The same split with only `fraction` of its samples, `(0, 1]`: `round(n * fraction)` (at
    /// least one) drawn without replacement with `seed`, kept in manifest order. The draw is a
    /// prefix of one permutation per seed, so for one seed the subsets are nested (the 1/16
    /// subset lies inside the 1/8 one) and every fraction of the same seed shares its samples
    /// with the larger ones. Batching, shuffling and augmentation are unchanged.
    ///
    /// # Errors
    /// A fraction outside `(0, 1]`.
    pub fn keep_fraction(self, fraction: f64, seed: u64) -> Result<Dataset> {
        if !(fraction > 0.0 && fraction <= 1.0) {
            return Err(Error::InvalidArgument(format!(
                "a training-set fraction must lie in (0, 1], got {fraction}"
            )));
        }
        let n = self.inner.ids.len();
        let keep = fraction_len(n, fraction);
        let mut order: Vec<usize> = (0..n).collect();
        Rng::derive(seed, &[tag("subset")]).shuffle(&mut order);
        let mut kept = order[..keep.min(n)].to_vec();
        kept.sort_unstable();
        let mut inner = (*self.inner).clone();
        inner.ids = kept.iter().map(|&i| self.inner.ids[i].clone()).collect();
        Ok(Dataset {
            inner: Arc::new(inner),
        })
    }

    /// The camera of the stored images (`camera.toml`).
    pub fn camera(&self) -> &Camera {
        &self.inner.camera
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.inner.manifest
    }

    /// Sample ids of the split, in manifest order.
    pub fn ids(&self) -> &[String] {
        &self.inner.ids
    }

    /// The frame the calibrated offsets need for this input: padding `[W - W_stored,
    /// H - H_stored]` on the right / bottom, half-pixel convention (as the stored camera was
    /// scaled).
    pub fn input_frame(&self) -> InputFrame {
        let [w, h] = self.inner.stored;
        let [ih, iw] = self.inner.input;
        InputFrame {
            padding: [iw - w, ih - h],
            convention: PixelConvention::HalfPixel,
        }
    }

    /// Number of batches per epoch.
    pub fn num_batches(&self) -> usize {
        let (n, b) = (self.inner.ids.len(), self.inner.config.batch_size);
        if self.inner.config.drop_last {
            n / b
        } else {
            n.div_ceil(b)
        }
    }

    /// The sample order of `epoch` (indices into [`Dataset::ids`]).
    pub fn epoch_order(&self, epoch: u64) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.inner.ids.len()).collect();
        if self.inner.config.shuffle {
            Rng::derive(self.inner.config.seed, &[tag("epoch"), epoch]).shuffle(&mut order);
        }
        order
    }

    /// Decodes sample `index` (no augmentation, stored size).
    pub fn load_sample(&self, index: usize) -> Result<Sample> {
        self.inner.load_sample(index)
    }
}

impl Inner {
    fn load_sample(&self, index: usize) -> Result<Sample> {
        let id = &self.ids[index];
        let size = self.stored;
        let root = &self.root;
        Ok(Sample {
            id: id.clone(),
            rgb: read_rgb(&sample_path(root, "rgb", id), size)?,
            depth: read_depth(
                &sample_path(root, "depth", id),
                size,
                self.manifest.depth_scale,
            )?,
            labels: read_labels(&sample_path(root, "labels", id), size)?,
            mask: read_mask(&sample_path(root, "mask", id), size)?,
        })
    }

    /// Loads, augments and pads the samples `indices` of `epoch`.
    fn load_batch(&self, indices: &[usize], epoch: u64) -> Result<RawBatch> {
        let samples: Vec<Sample> = indices
            .par_iter()
            .map(|&i| {
                let mut s = self.load_sample(i)?;
                self.augment(&mut s, epoch, i);
                Ok(s)
            })
            .collect::<Result<_>>()?;
        let [w, h] = self.stored;
        let [ih, iw] = self.input;
        let (b, plane) = (samples.len(), ih * iw);
        let mut raw = RawBatch {
            size: [b, ih, iw],
            image: vec![0.0; b * 3 * plane],
            depth: vec![0.0; b * plane],
            labels: vec![IGNORE_LABEL; b * plane],
            mask: vec![false; b * plane],
            ids: Vec::with_capacity(b),
        };
        for (k, s) in samples.into_iter().enumerate() {
            for v in 0..h {
                for u in 0..w {
                    let i = v * w + u;
                    let o = v * iw + u;
                    for c in 0..3 {
                        raw.image[(k * 3 + c) * plane + o] = s.rgb[i][c] as f32 / 255.0;
                    }
                    raw.depth[k * plane + o] = s.depth[i];
                    let l = s.labels[i];
                    if (l as usize) < NUM_CLASSES {
                        raw.labels[k * plane + o] = l as i64;
                    }
                    raw.mask[k * plane + o] = s.mask[i];
                }
            }
            raw.ids.push(s.id);
        }
        Ok(raw)
    }

    /// Applies the configured augmentations with randomness keyed by (seed, epoch, sample).
    fn augment(&self, s: &mut Sample, epoch: u64, index: usize) {
        let aug = self.config.augment;
        if !aug.hflip && aug.jitter.is_none() {
            return;
        }
        let mut rng = Rng::derive(self.config.seed, &[tag("augment"), epoch, index as u64]);
        let [w, h] = self.stored;
        if aug.hflip && rng.chance(0.5) {
            for v in 0..h {
                let row = v * w..(v + 1) * w;
                s.rgb[row.clone()].reverse();
                s.depth[row.clone()].reverse();
                s.labels[row.clone()].reverse();
                s.mask[row].reverse();
            }
        }
        if let Some(j) = aug.jitter {
            let mut factor = |x: f32| rng.uniform(1.0 - x as f64, 1.0 + x as f64) as f32;
            let (b, c, sat) = (
                factor(j.brightness),
                factor(j.contrast),
                factor(j.saturation),
            );
            let grey = |p: [f32; 3]| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
            let inside = &self.inside;
            let (sum, n) = s
                .rgb
                .iter()
                .zip(inside)
                .filter(|(_, &i)| i)
                .fold((0.0f64, 0usize), |(a, n), (p, _)| {
                    (a + grey(p.map(|x| x as f32)) as f64, n + 1)
                });
            let mean = if n > 0 { (sum / n as f64) as f32 } else { 0.0 };
            for (p, &i) in s.rgb.iter_mut().zip(inside) {
                if !i {
                    *p = [0; 3]; // outside the image stays black
                    continue;
                }
                let mut q = p.map(|x| x as f32 * b);
                q = q.map(|x| (x - mean * b) * c + mean * b);
                let g = grey(q);
                q = q.map(|x| g + (x - g) * sat);
                *p = q.map(|x| x.round().clamp(0.0, 255.0) as u8);
            }
        }
    }
}

/// The network input `[H, W]` of `[h, w]` stored images (see [`InputSize`]).
fn input_size(input: InputSize, [h, w]: [usize; 2]) -> Result<[usize; 2]> {
    Ok(match input {
        InputSize::Stored => [h, w],
        InputSize::Exact([ih, iw]) => {
            if ih < h || iw < w {
                return Err(Error::InvalidArgument(format!(
                    "input size {ih}x{iw} is smaller than the stored images {h}x{w} \
                     (nothing is resized; regenerate at the size you need)"
                )));
            }
            [ih, iw]
        }
        InputSize::Multiple(m) => {
            if m == 0 {
                return Err(Error::InvalidArgument("input multiple must be > 0".into()));
            }
            [h.div_ceil(m) * m, w.div_ceil(m) * m]
        }
    })
}

/// Horizontal flips keep `camera` (read from `camera_path`) valid: a mirror-symmetric model
/// with its principal point within [`FLIP_MAX_PP_OFFSET_PX`] of the image centre.
fn check_flippable(camera: &Camera, camera_path: &Path) -> Result<()> {
    let [w, _] = camera.size();
    // Radially symmetric models mirror onto themselves about the vertical line through
    // the principal point; radial-tangential (p2, also in Mei's) and Scaramuzza (affine c, d, e) in
    // general do not.
    let symmetric = match camera {
        Camera::KannalaBrandt(_)
        | Camera::Pinhole(_)
        | Camera::DoubleSphere(_)
        | Camera::Unified(_)
        | Camera::ExtendedUnified(_)
        | Camera::Fov(_)
        | Camera::Equirectangular(_) => true,
        Camera::PinholeRadTan(_) | Camera::Mei(_) | Camera::Scaramuzza(_) => false,
    };
    if !symmetric {
        return Err(Error::data(
            camera_path,
            format!(
                "field `model`: horizontal flips need a mirror-symmetric model; a {} \
                 camera is not one in general",
                camera.model_name()
            ),
        ));
    }
    let cx = camera.project([0.0, 0.0, 1.0]).map_or(f64::NAN, |c| c[0]);
    let off = cx - (w as f64 - 1.0) / 2.0;
    let centred = off.abs() <= FLIP_MAX_PP_OFFSET_PX; // false for NaN
    if !centred {
        return Err(Error::data(
            camera_path,
            format!(
                "field `cx`: horizontal flips need a centred principal point, but cx = \
                 {cx} is {off:+.3} px from (W - 1) / 2 = {} (limit \
                 {FLIP_MAX_PP_OFFSET_PX} px): a flipped image would no longer match \
                 the calibration",
                (w as f64 - 1.0) / 2.0
            ),
        ));
    }
    Ok(())
}

/// Every file of the samples `ids` of `split` exists under `root`.
fn check_samples(root: &Path, split: Split, ids: &[String]) -> Result<()> {
    for id in ids {
        for sub in ["rgb", "depth", "labels", "mask"] {
            let p = sample_path(root, sub, id);
            if !p.is_file() {
                return Err(Error::data(
                    &p,
                    format!("missing: sample `{id}` of split {split} in manifest.json"),
                ));
            }
        }
    }
    Ok(())
}

/// A batch as plain buffers (built off the consumer's thread).
struct RawBatch {
    /// `[B, H, W]`.
    size: [usize; 3],
    image: Vec<f32>,
    depth: Vec<f32>,
    labels: Vec<i64>,
    mask: Vec<bool>,
    ids: Vec<String>,
}

impl RawBatch {
    fn into_batch(self) -> Batch {
        let [b, h, w] = self.size.map(|x| x as i64);
        Batch {
            image: Tensor::from_slice(&self.image).view([b, 3, h, w]),
            depth: Tensor::from_slice(&self.depth).view([b, 1, h, w]),
            labels: Tensor::from_slice(&self.labels).view([b, h, w]),
            mask: Tensor::from_slice(&self.mask).view([b, 1, h, w]),
            ids: self.ids,
        }
    }
}

/// Batches assembled by a background thread, `prefetch` ahead.
struct Prefetch {
    rx: Option<Receiver<Result<RawBatch>>>,
    worker: Option<JoinHandle<()>>,
}

impl Iterator for Prefetch {
    type Item = Result<Batch>;
    fn next(&mut self) -> Option<Result<Batch>> {
        let item = self.rx.as_ref()?.recv().ok()?;
        Some(item.map(RawBatch::into_batch))
    }
}

impl Drop for Prefetch {
    fn drop(&mut self) {
        // Closing the channel stops the worker after the batch it is assembling.
        self.rx.take();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

impl BatchSource for Dataset {
    fn len(&self) -> usize {
        self.inner.ids.len()
    }

    fn input_size(&self) -> [i64; 2] {
        self.inner.input.map(|x| x as i64)
    }

    fn batches(&self, epoch: u64, skip: usize) -> Box<dyn Iterator<Item = Result<Batch>> + '_> {
        let order = self.epoch_order(epoch);
        let cfg = self.inner.config;
        let chunks: Vec<Vec<usize>> = order
            .chunks(cfg.batch_size)
            .filter(|c| !cfg.drop_last || c.len() == cfg.batch_size)
            .skip(skip)
            .map(<[usize]>::to_vec)
            .collect();
        let (tx, rx) = sync_channel(cfg.prefetch);
        let inner = Arc::clone(&self.inner);
        let worker = std::thread::Builder::new()
            .name("calibconv-loader".into())
            .spawn(move || {
                for chunk in chunks {
                    let batch = inner.load_batch(&chunk, epoch);
                    let failed = batch.is_err();
                    if tx.send(batch).is_err() || failed {
                        break;
                    }
                }
            })
            .expect("spawn the loader thread");
        Box::new(Prefetch {
            rx: Some(rx),
            worker: Some(worker),
        })
    }
}

#[cfg(test)]
mod tests;
