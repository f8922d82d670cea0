//! `calibconv synth`: data sets of perspective, fisheye and rectified views rendered from
//! panoramas (procedural, or Stanford 2D-3D-S), written in the layout of [`crate::data`].
//!
//! # Configuration (`data/synth.toml`, embedded in the binary as [`DEFAULT_CONFIG`])
//!
//! ```toml
//! seed = 2024                  # every scene, orientation and split follows from it
//! out = "data/synth"           # each set is written to OUT/NAME
//!
//! [panoramas]
//! source = "procedural"        # or "stanford" (then stanford_root is required)
//! count = 48                   # procedural: how many; stanford: 0 = all, N = an evenly spaced subset
//! height = 256                 # panorama height in pixels (width = 2 height); Stanford
//!                              # panoramas (2048 high) are box-filtered down to it
//! split = { train = 0.8, val = 0.1, test = 0.1 }   # fractions of panoramas (stanford: only
//!                              # `val` is used; test is area 5, the official fold 1)
//! # stanford_root = "/data/2D-3D-S"
//! # stanford_labels = "/data/2D-3D-S/assets/semantic_labels.json"   # the default
//!
//! [views]
//! per_panorama = 4             # views per panorama and set
//! pitch_max_deg = 10.0         # orientations: yaw uniform, |pitch| and |roll| uniform below these
//! roll_max_deg = 5.0
//! supersample = 2              # k x k RGB rays per pixel (depth / labels: the centre ray)
//!
//! [[set]]                      # one data set folder per [[set]]
//! name = "f195"                # folder name
//! kind = "fisheye"             # "pers" (pinhole camera), "fisheye", "rectified" (fisheye
//!                              # re-projected to a pinhole; FOV < 180 only)
//! camera = "data/cameras/f195.toml"   # relative paths are relative to the working directory
//!                              # (the embedded default's cameras are embedded too, see
//!                              # [`DEFAULT_CAMERAS`])
//! width = 128                  # stored width; the camera is scaled by width / camera width
//!                              # (half-pixel convention) and camera.toml holds the result
//! # rectify_hfov_deg = 120.0   # rectified only: the pinhole's horizontal FOV (default: keep
//!                              # the fisheye's focal length)
//! ```
//!
//! # Guarantees
//!
//! - **Deterministic**: the same configuration and seed give byte-identical files on any
//!   machine and thread count (scenes, orientations and splits come from [`crate::data::rng`]
//!   streams keyed by `(seed, panorama, view)`; PNG encoding settings are fixed).
//! - **Resumable**: every file is written atomically (temporary file + rename) and the manifest
//!   says `complete: false` until the end, so an interrupted run leaves only whole files; the
//!   same command again skips every sample whose five files exist with the right size.
//! - **Safe**: a folder holding a manifest from another generator, generator version, seed,
//!   configuration or split, or a non-empty folder without a manifest, is refused unless
//!   `force`; with `force` every sample is rewritten and sample files of ids no longer in the
//!   set are removed from the five sample folders (nothing else is touched).
//!
//! The configuration (its schema and checks) is [`config`]; the job runner that checks the
//! folders and writes the samples is [`run`]; the panoramas come from a
//! [`crate::data::source::PanoramaSource`].

pub mod config;
pub mod run;

pub use crate::data::format::{GENERATOR, GENERATOR_VERSION};
pub use crate::data::source::{assign_splits, PanoramaSource, ProceduralSource};
pub use config::{
    RawPanoramas, RawSet, RawSplit, RawSynthConfig, RawViews, SetPlan, SourceKind, SourceSpec,
    SynthPlan, ViewKind, DEFAULT_CAMERAS, DEFAULT_CONFIG,
};
pub use run::{
    prepare_set, run_jobs, sample_id, synthesize, GenerateOptions, RunReport, SetJob, SetRenderer,
};
