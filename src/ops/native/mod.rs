//! The native CPU kernels (the C++ sources beside this file, entry point `deform.cpp`, compiled
//! by `build.rs` against libtorch): a `torch::autograd::Function` called through one C entry
//! point that takes and returns `at::Tensor*` handles (tch's `Tensor::as_ptr` /
//! `Tensor::from_ptr`), and reports C++ exceptions as an error message instead of letting them
//! cross into Rust.

use std::ffi::{c_char, CStr};

use tch::Tensor;
use torch_sys::C_tensor;

use super::settings::sealed::Entry;
use super::PlannedCall;
use crate::error::{Error, Result};

extern "C" {
    /// See `deform.cpp`. Returns null on success (`*out` then holds a new tensor handle that
    /// the caller owns), else a message to release with `calibconv_free_error`.
    fn calibconv_deform_conv2d_cpu(
        input: *const C_tensor,
        weight: *const C_tensor,
        bias: *const C_tensor,
        top_left: *const C_tensor,
        frac: *const C_tensor,
        rows: *const C_tensor,
        ho: i64,
        wo: i64,
        groups: i64,
        per_item: i32,
        wrap: i32,
        out_layout: i32,
        out: *mut *mut C_tensor,
    ) -> *mut c_char;
    fn calibconv_free_error(message: *mut c_char);
    /// See `deform.cpp`: caps the level when `cap >= 0`, returns the level in use.
    fn calibconv_native_small_isa(cap: i32) -> i32;
    /// See `deform.cpp`: sets the GEMM library when `choice >= 0` (0 the CPU's default, 1
    /// oneDNN, 2 the BLAS), returns the one in use (1 oneDNN, 2 the BLAS).
    fn calibconv_native_gemm(choice: i32) -> i32;
    /// See `deform.cpp`: sets the library of the large weights' products when `choice >= 0` (0
    /// the CPU's default, 1 the kernels, 2 the BLAS), returns the one in use (1 or 2).
    fn calibconv_native_large_weights(choice: i32) -> i32;
    /// See `deform.cpp`: poisons (1) or stops poisoning (0) the scratch buffers that every
    /// pass must write before it reads them; returns whether they are poisoned.
    #[cfg(test)]
    fn calibconv_native_poison_scratch(on: i32) -> i32;
}

/// Fills the native kernels' uninitialised scratch buffers with NaN from now on, for the whole
/// process (the tests that hold the kernels to ATen: a value read before it was written then
/// shows, where fresh zero pages would hide it).
#[cfg(test)]
pub(super) fn poison_scratch() {
    // SAFETY: a plain function of an integer; it only writes an atomic.
    let on = unsafe { calibconv_native_poison_scratch(1) };
    assert_eq!(on, 1, "scratch poisoning must take effect");
}

/// Reads a process-wide setting of the kernels (see [`super::NativeSetting`]); with `choice`,
/// first sets it (`Some(None)`: its default, else a value's code). Returns the code of the value
/// in use.
pub(super) fn setting(entry: Entry, choice: Option<Option<i32>>) -> Option<i32> {
    // The entry points' encoding: `-1` keeps the setting, else the choice's code. The level of
    // the few-output-channel kernels is a cap, whose default (none) is the highest level; for
    // the others `0` asks for the default.
    let code = match (entry, choice) {
        (_, None) => -1,
        (_, Some(Some(code))) => code,
        (Entry::SmallIsa, Some(None)) => super::SmallKernelIsa::Avx512 as i32,
        (Entry::Gemm | Entry::LargeWeights, Some(None)) => 0,
    };
    // SAFETY: plain functions of an integer; they only read and write an atomic.
    let in_use = unsafe {
        match entry {
            Entry::SmallIsa => calibconv_native_small_isa(code),
            Entry::Gemm => calibconv_native_gemm(code),
            Entry::LargeWeights => calibconv_native_large_weights(code),
        }
    };
    Some(in_use)
}

/// The layout of the native op's output (the kernels write either layout from either input
/// layout, so none costs a conversion).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum OutLayout {
    /// The input's (NCHW or channels-last), as `conv2d`.
    Input = 0,
    /// Channels-last.
    ChannelsLast = 1,
    /// NCHW.
    Nchw = 2,
}

/// The deformable convolution of CPU tensors through the native kernels, its output in
/// `out_layout`. The operands are checked (see [`PlannedCall::checked`]).
pub(super) fn deform_conv2d_cpu(call: &PlannedCall, out_layout: OutLayout) -> Result<Tensor> {
    let plan = call.plan;
    let frac = plan.frac();
    let frac = frac.to_kind(call.input.kind());
    let [ho, wo] = plan.output_size();
    let mut out: *mut C_tensor = std::ptr::null_mut();
    // SAFETY: every pointer is a live tensor handle borrowed for the duration of the call (the
    // C++ side copies the handles it keeps), `bias` may be null, and `out` is written only on
    // success with a fresh handle whose ownership passes to us.
    let err = unsafe {
        calibconv_deform_conv2d_cpu(
            call.input.as_ptr(),
            call.weight.as_ptr(),
            call.bias.map_or(std::ptr::null(), |b| b.as_ptr()),
            plan.top_left().as_ptr(),
            frac.as_ptr(),
            plan.rows().as_ptr(),
            ho,
            wo,
            call.groups,
            i32::from(plan.batch().is_some()),
            i32::from(plan.border() == super::plan::Border::WrapX),
            out_layout as i32,
            &mut out,
        )
    };
    if !err.is_null() {
        // SAFETY: a NUL-terminated message from the C++ side, released exactly once below.
        let message = unsafe { CStr::from_ptr(err) }
            .to_string_lossy()
            .into_owned();
        unsafe { calibconv_free_error(err) };
        return Err(Error::Torch(tch::TchError::Torch(message)));
    }
    if out.is_null() {
        return Err(Error::Torch(tch::TchError::Torch(
            "native deform_conv2d returned no tensor".into(),
        )));
    }
    // SAFETY: `out` is a fresh, owned `at::Tensor*` allocated with `new` by the C++ side, which
    // is what tch frees on drop.
    Ok(unsafe { Tensor::from_ptr(out) })
}
