//! Data: synthetic indoor panoramas, fisheye / perspective / rectified view synthesis, the
//! Stanford 2D-3D-S loader, and batches for training (paper Section 4: *Pers*, *F165*, *F195*
//! and rectified images synthesised from panoramas).
//!
//! The data path, one module per step:
//!
//! - [`panorama`]: equirectangular panoramas (RGB, metric distance, labels) and the seeded
//!   procedural indoor scenes that render them by analytic ray casting;
//! - [`stanford`]: the same panoramas decoded from a Stanford 2D-3D-S copy;
//! - [`views`]: fisheye, perspective and rectified views of a panorama for any camera, at
//!   random orientations, with a validity mask;
//! - [`synth`]: `calibconv synth`: data set folders (below), deterministic and resumable;
//! - [`format`](mod@format): the PNG encodings and the manifest of those folders;
//! - [`loader`]: a folder served as [`Batch`]es ([`loader::Dataset`] implements
//!   [`BatchSource`]);
//! - [`rng`]: the seeded generator everything random goes through.
//!
//! # The contract with training (do not change without updating both sides)
//!
//! Training and evaluation see data only through [`BatchSource`] and [`Batch`]:
//! - `image`: `[B, 3, H, W]` float32 RGB in `[0, 1]` (8-bit value / 255, no mean/std, as the
//!   public PyTorch U-Net);
//! - `depth`: `[B, 1, H, W]` float32 metres, `0` where missing;
//! - `labels`: `[B, H, W]` int64 class ids `0..NUM_CLASSES` in [`CLASSES`] order, or
//!   [`IGNORE_LABEL`] for unknown / invalid pixels (PyTorch's default `ignore_index`): unknown
//!   class, outside the fisheye image circle, padding. A pixel whose depth alone is missing
//!   keeps its class (its `mask` is false);
//! - `mask`: `[B, 1, H, W]` bool, true on valid pixels (inside the fisheye image circle, depth
//!   present, not padding).
//!
//! `H, W` is the network input: the stored image padded on the right / bottom (padding pixels
//! are zeros with `mask` false), matching the `InputFrame` padding the calibrated offsets use.
//!
//! # On-disk data set (written by `calibconv synth`, read by [`BatchSource`] implementations)
//!
//! ```text
//! DATASET/manifest.json     generator, generator_version, seed, camera, counts, splits {train,
//!                           val, test: [ids]}, depth_scale (metres per unit), classes; also
//!                           complete, name, kind, width, height, unknown_label, config
//!                           (see format::Manifest)
//! DATASET/camera.toml       the camera the views were rendered with (at the stored resolution)
//! DATASET/rgb/ID.png        8-bit RGB
//! DATASET/depth/ID.png      16-bit grey; metres = value * depth_scale; 0 = missing
//! DATASET/labels/ID.png     8-bit grey; class id in CLASSES order; 255 = unknown
//! DATASET/mask/ID.png       8-bit grey; 255 = valid
//! DATASET/previews/ID.png   colourised RGB | depth | labels, for people
//! ```

pub mod format;
pub mod loader;
pub mod memory;
pub mod panorama;
pub mod rng;
pub mod source;
pub mod stanford;
pub mod synth;
pub mod toy;
pub mod views;

use tch::Tensor;

use crate::error::Result;

/// The 13 Stanford 2D-3D-S classes, in the alphabetical order public loaders use for ids.
pub const CLASSES: [&str; 13] = [
    "beam", "board", "bookcase", "ceiling", "chair", "clutter", "column", "door", "floor", "sofa",
    "table", "wall", "window",
];

/// The id of the class `name`: its index in [`CLASSES`]. A `const` evaluated at compile time,
/// so a constant naming no class is a compile error.
pub const fn class_id(name: &str) -> u8 {
    let mut i = 0;
    while i < CLASSES.len() {
        let (a, b) = (CLASSES[i].as_bytes(), name.as_bytes());
        if a.len() == b.len() {
            let mut k = 0;
            while k < a.len() && a[k] == b[k] {
                k += 1;
            }
            if k == a.len() {
                return i as u8;
            }
        }
        i += 1;
    }
    panic!("not a class name");
}

/// Number of semantic classes (unknown excluded).
pub const NUM_CLASSES: usize = CLASSES.len();

/// Label of unknown / invalid pixels in tensors (PyTorch's default `ignore_index`).
pub const IGNORE_LABEL: i64 = -100;

/// Label of unknown pixels in label PNGs.
pub const UNKNOWN_PNG_LABEL: u8 = 255;

/// One batch, see the module docs for shapes and units.
#[derive(Debug)]
pub struct Batch {
    /// `[B, 3, H, W]` float32 RGB in `[0, 1]`.
    pub image: Tensor,
    /// `[B, 1, H, W]` float32 metres, 0 where missing.
    pub depth: Tensor,
    /// `[B, H, W]` int64 class ids or [`IGNORE_LABEL`].
    pub labels: Tensor,
    /// `[B, 1, H, W]` bool, true on valid pixels.
    pub mask: Tensor,
    /// Sample ids, in batch order.
    pub ids: Vec<String>,
}

/// Something that serves batches in a deterministic order per epoch.
pub trait BatchSource {
    /// Number of samples (not batches).
    fn len(&self) -> usize;
    /// Whether there are no samples.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Network input size `[H, W]` of every batch.
    fn input_size(&self) -> [i64; 2];
    /// The batches of `epoch`; the order depends only on the source's seed and `epoch`, so a
    /// resumed run sees the same data order. `skip` batches at the start are not loaded.
    fn batches(&self, epoch: u64, skip: usize) -> Box<dyn Iterator<Item = Result<Batch>> + '_>;
}
