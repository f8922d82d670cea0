//! The integration tests that can share a process, as one test binary: each file below is a
//! module, and its tests run in parallel threads next to every other module's (one binary to
//! link instead of one per file, and one process that runs them all).
//!
//! What a test here must not do, because every other test of the binary shares its process:
//! change the current directory (tests pass explicit paths; Cargo runs them in the package root,
//! against which the shipped experiment files' relative paths resolve), set environment
//! variables (set them on the `Command` of a child process instead), change a process-wide
//! libtorch or native-kernel setting (thread counts, `GemmLibrary`, `LargeWeights`), or rely on
//! the exact draws of libtorch's global random generator, which any other thread may draw from
//! or reseed. Tests that need one of these have a binary of their own, next to this folder:
//! `gemm_library.rs`, `large_weights.rs` and `small_output_layout.rs` (process-wide settings),
//! `train_e2e.rs` (networks initialised from seeds, compared bit for bit), `cuda.rs` (built on
//! its own for the GPU machine by `tools/gpu/build.sh`).

#[path = "../common/mod.rs"]
mod common;

mod build_links;
mod camera_import;
mod cli;
mod data;
mod equirect;
mod experiments;
mod layering;
mod lock;
mod oracle_opencv;
mod oracle_opencv_radtan;
mod oracle_torchvision;
mod oracle_unet;
mod pytorch_parity;
mod report;
mod seeds;
mod stop_signal;
mod sweep;
mod tensorboard;
mod train_dataset;
