//! Embeds an rpath to libtorch (from torch-sys's `DEP_TCH_LIBTORCH_LIB`) so binaries and tests
//! run without `LD_LIBRARY_PATH`, checks that the venv's torch is the version tch expects, and
//! compiles the native CPU kernels (`src/ops/native/*.cpp`) against the same libtorch
//! headers (C++17, the ABI torch-sys uses, OpenMP for `at::parallel_for`); on success it sets
//! `cfg(calibconv_native)`, on failure it warns and the crate uses the ATen composition (and the
//! test `native_kernels_are_built` fails unless `CALIBCONV_ALLOW_NO_NATIVE=1`). Linking to
//! libtorch itself comes from torch-sys.

use std::path::PathBuf;

const TORCH_VERSION: &str = "2.13.0";

/// The native kernels' sources, one per pass (deform.cpp holds the entry point).
const NATIVE_SRC: [&str; 8] = [
    "src/ops/native/deform.cpp",
    "src/ops/native/forward.cpp",
    "src/ops/native/gather.cpp",
    "src/ops/native/grad_input.cpp",
    "src/ops/native/grad_weight.cpp",
    "src/ops/native/layout.cpp",
    "src/ops/native/padding.cpp",
    "src/ops/native/small.cpp",
];
/// The headers they include (a change to one rebuilds the kernels).
const NATIVE_HEADERS: [&str; 4] = [
    "src/ops/native/deform.h",
    "src/ops/native/gather.h",
    "src/ops/native/simd.h",
    "src/ops/native/small_kernels.h",
];

fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    println!("cargo:rustc-check-cfg=cfg(calibconv_native)");
    let Ok(lib) = std::env::var("DEP_TCH_LIBTORCH_LIB") else {
        return;
    };
    let lib = PathBuf::from(&lib);
    let lib = lib.canonicalize().unwrap_or(lib);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    // The pip wheel has no `build-version` file, so torch-sys cannot check it: do it here.
    let version_py = lib.join("..").join("version.py");
    if let Ok(text) = std::fs::read_to_string(&version_py) {
        println!("cargo:rerun-if-changed={}", version_py.display());
        let found = text
            .lines()
            .find_map(|l| l.strip_prefix("__version__ = "))
            .map(|v| v.trim_matches(|c| c == '\'' || c == '"').to_string())
            .unwrap_or_default();
        if !found.starts_with(TORCH_VERSION) {
            panic!(
                "calibconv needs torch=={TORCH_VERSION} (tch 0.26), found {found:?} in {}; run `make setup`",
                version_py.display()
            );
        }
    }
    compile_native(&lib);
}

/// Compiles [`NATIVE_SRC`] into a static library linked into the crate and sets
/// `cfg(calibconv_native)`; on failure warns and leaves the ATen composition as the CPU path.
fn compile_native(lib: &std::path::Path) {
    for path in NATIVE_SRC.iter().chain(&NATIVE_HEADERS) {
        println!("cargo:rerun-if-changed={path}");
    }
    println!("cargo:rerun-if-env-changed=LIBTORCH_CXX11_ABI");
    let include = lib.join("..").join("include");
    let abi = std::env::var("LIBTORCH_CXX11_ABI").unwrap_or_else(|_| "1".to_string());
    let built = cc::Build::new()
        .cpp(true)
        .pic(true)
        .std("c++17")
        .opt_level(3)
        // libtorch's headers are system headers: their warnings are not ours.
        .flag("-isystem")
        .flag(include.to_str().expect("utf-8 libtorch path"))
        .flag("-isystem")
        .flag(
            include
                .join("torch/csrc/api/include")
                .to_str()
                .expect("utf-8 libtorch path"),
        )
        .flag(format!("-D_GLIBCXX_USE_CXX11_ABI={abi}"))
        .flag("-DGLOG_USE_GLOG_EXPORT")
        .flag("-fopenmp")
        .flag("-Wall")
        .flag("-Wextra")
        .files(NATIVE_SRC)
        .try_compile("calibconv_native");
    match built {
        Ok(()) => println!("cargo:rustc-cfg=calibconv_native"),
        // Without a C++17 compiler the crate still builds, on the ATen composition alone; the
        // test `ops::tests::native_kernels_are_built` then fails unless
        // CALIBCONV_ALLOW_NO_NATIVE=1 says that this is intended.
        Err(e) => println!(
            "cargo:warning=native CPU kernels not built ({e}); the deformable convolution uses \
             the (slower) ATen composition on the CPU, and the tests fail unless \
             CALIBCONV_ALLOW_NO_NATIVE=1"
        ),
    }
}
