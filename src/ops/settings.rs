//! The process-wide settings of the native CPU kernels: which code computes a product, never
//! what it computes beyond rounding. One trait, [`NativeSetting`], reads and sets each of them;
//! the enums name their values ([`SmallKernelIsa`], [`GemmLibrary`], [`LargeWeights`]).
//!
//! A setting is one atomic of the native code, shared by every thread for the rest of the
//! process. A choice is a request: the value in use is what this CPU and this libtorch allow
//! (oneDNN where libtorch has it, an instruction-set level the CPU has). Without the native
//! kernels every setting is fixed (at the first of its values): there is nothing to choose.

use super::native;

/// A process-wide setting of the native CPU kernels (see the module docs): one per enum of its
/// values. For tests and A/B timings (`calibconv bench --small-kernels`, `--gemm`,
/// `--large-weights`).
pub trait NativeSetting: sealed::Native {
    /// The value this process uses.
    fn current() -> Self {
        in_use(native::setting(Self::ENTRY, None))
    }

    /// Sets the setting for the rest of the process (every thread; `None`: its default) and
    /// returns the value now in use.
    fn set(choice: Option<Self>) -> Self {
        in_use(native::setting(Self::ENTRY, Some(choice.map(Self::code))))
    }
}

impl<T: sealed::Native> NativeSetting for T {}

/// The value of `S` whose discriminant the native code returned: the first of its values without
/// the native kernels (`None`) or for a code this build does not know.
fn in_use<S: sealed::Native>(code: Option<i32>) -> S {
    code.and_then(|c| S::VALUES.iter().copied().find(|v| v.code() == c))
        .unwrap_or(S::VALUES[0])
}

/// What ties a setting's enum to the native code; not for implementing elsewhere.
pub(super) mod sealed {
    /// The native entry point of a setting (see `native::setting`).
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub enum Entry {
        SmallIsa,
        Gemm,
        LargeWeights,
    }

    /// A setting's values and its entry point (the values' discriminants are the native codes).
    pub trait Native: Copy + 'static {
        /// The native entry point.
        const ENTRY: Entry;
        /// Every value, the one in use without the native kernels first.
        const VALUES: &'static [Self];
        /// The native code of the value (its discriminant).
        fn code(self) -> i32;
    }
}

/// The instruction-set level of the native few-output-channel kernels (float32, one group, 8
/// to 1024 output channels): their register blocking is compiled per level and picked
/// at run time from the CPU.
///
/// As a [`NativeSetting`], the choice is a cap: the level in use is the CPU's, at most the one
/// set (both levels compute identical values; `SmallKernelIsa::None` sends those layers through
/// the GEMM library); the default is no cap.
/// (The discriminants are the native code's `SmallIsa`.)
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
#[repr(i32)]
pub enum SmallKernelIsa {
    /// Not used (no native kernels, not x86-64, or a CPU without AVX2 and FMA): such layers
    /// go through the GEMM library like any other.
    None = 0,
    /// x86-64-v3 (AVX2, FMA): 16 registers of 8 floats; 8, 16 and 32 outputs (64 and 128 go
    /// through the GEMM library, faster at this level).
    Avx2 = 1,
    /// x86-64-v4 (AVX-512): 32 registers of 16 floats.
    Avx512 = 2,
}

impl sealed::Native for SmallKernelIsa {
    const ENTRY: sealed::Entry = sealed::Entry::SmallIsa;
    const VALUES: &'static [Self] = &[Self::None, Self::Avx2, Self::Avx512];
    fn code(self) -> i32 {
        self as i32
    }
}

/// The library of the float32 products of one group that the few-output-channel kernels do not
/// take (more than 1024 or other output counts, weights over 36 MiB; the weight gradient from 32
/// outputs on where those kernels are absent). Both give the same values up to rounding.
///
/// As a [`NativeSetting`]: the default is the BLAS; oneDNN only where libtorch has it
/// (`calibconv bench --gemm`). Without the native kernels, whose ATen composition multiplies
/// with `at::mm`-style ops, it is the BLAS.
/// (The discriminants are the native code's.)
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(i32)]
pub enum GemmLibrary {
    /// oneDNN, as a 1x1 convolution (the library `conv2d` uses), for A/B timings: it reorders
    /// the weight on every call.
    OneDnn = 1,
    /// The BLAS (`at::mm`, libtorch's MKL), the default: at the shapes left to the library
    /// (128-1024 channels) faster than oneDNN's 1x1 convolution on an AMD Zen 3 (AVX2) and on a
    /// Zen 4 (AVX-512), with less memory (docs/bench/cpu-kernels.md).
    Blas = 2,
}

impl sealed::Native for GemmLibrary {
    const ENTRY: sealed::Entry = sealed::Entry::Gemm;
    const VALUES: &'static [Self] = &[Self::Blas, Self::OneDnn];
    fn code(self) -> i32 {
        self as i32
    }
}

/// The library of the products of large weights (see [`LargeWeights::Blas`])
/// where the few-output-channel kernels exist. Both give the same values up to rounding.
///
/// As a [`NativeSetting`]: the default is the CPU's (`calibconv bench --large-weights`).
/// Without the native kernels it is [`LargeWeights::Kernels`], where there are none to choose.
/// (The discriminants are the native code's.)
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(i32)]
pub enum LargeWeights {
    /// The few-output-channel kernels multiply every product (the default except on Intel CPUs
    /// with MKL).
    Kernels = 1,
    /// The BLAS computes the column and weight gradients of weights over 4 MiB (256->512 and
    /// 512->256 on) and the forward of such weights on fewer than 1024 output pixels a pass
    /// (`classic`'s 512->1024 and 1024->1024 on 16x16 maps at B2): the default where the BLAS is
    /// MKL on an Intel CPU, which runs its AVX-512 code there only (docs/bench/cpu-kernels.md).
    Blas = 2,
}

impl sealed::Native for LargeWeights {
    const ENTRY: sealed::Entry = sealed::Entry::LargeWeights;
    const VALUES: &'static [Self] = &[Self::Kernels, Self::Blas];
    fn code(self) -> i32 {
        self as i32
    }
}
