//! # calibconv-geometry: camera models and calibrated kernel offsets, in plain Rust
//!
//! The tensor-free floor of calibconv (no tch, no libtorch: its tests run without either).
//! Data flows one way:
//!
//! - [`vec3`]: the 3-vector math (normalise, cross, matrix-vector) the floors above share.
//! - [`camera`]: camera models in `f64` (Kannala-Brandt, pinhole, radial-tangential, double
//!   sphere, (extended) unified, Mei, FOV, Scaramuzza, equirectangular) behind one trait, read
//!   from TOML camera files (`data/cameras/`) or imported from other tools' calibrations
//!   ([`camera::import`]). Each model's file owns its formulas, its camera-file schema and its
//!   checks; constructors validate.
//! - [`kernel`]: the paper's "fisheye calibrated kernel" (Section 3.2): for a layer geometry and
//!   feature-map size, the offsets of every kernel tap relative to the regular deformable grid,
//!   as plain data ([`kernel::Offsets`]: `Vec<f32>` in torchvision's layout), computed in
//!   parallel. The `calibconv` crate turns them into tensors and caches them.
//! - [`plan`]: the sampling plan's arithmetic over slices (bilinear corners and fractions of
//!   every sample of a deformable convolution with fixed offsets): one implementation for the
//!   `calibconv` crate's tensors and the Python package's numpy arrays.
//! - [`error`]: the crate's one error enum; `calibconv::Error` wraps it with the same messages.
//!
//! ## Adding a camera model
//!
//! A model is one file plus one line:
//!
//! 1. Write `camera/<model>.rs`: the struct (its intrinsics through [`camera::Intrinsics`] where
//!    it has a focal length), its formulas with their equations in doc comments,
//!    `impl CameraModel` (`project` / `unproject` return `Option`, never NaN), a
//!    `project_jacobian`, its validating `new` (returns `Result<_, Invalid>`), and its camera
//!    file schema: a `Raw` struct declared with `raw_camera_file!` and
//!    `impl CameraFile` (`MODEL`, the `model =` name; `from_raw`, which calls `new`; `fields`,
//!    what `to_toml` writes). Iterative inverses use `camera::solve`.
//! 2. Add its line to the `camera_models!` table in `camera/mod.rs`:
//!    `Variant(module::Type),`. That declares the module, re-exports the type, adds the
//!    [`camera::Camera`] variant, the `model =` name to [`camera::MODELS`] and the reader, and
//!    dispatches `project / unproject / size / fov / rescaled / ... / to_toml` to it.
//! 3. Ship a camera file of the model in `data/cameras/`: the sweep test over every shipped
//!    camera fails until one exists, and its `match`es over [`camera::Camera`] (principal point,
//!    pixel scale, domain) stop compiling until the model says where its domain ends.

pub mod camera;
pub mod error;
pub mod kernel;
pub mod memory;
pub mod plan;
pub mod vec3;

pub use error::{Error, Result};
