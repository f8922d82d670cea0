//! Embeds an rpath to libtorch (from torch-sys's `DEP_TCH_LIBTORCH_LIB`) so binaries and tests
//! run without `LD_LIBRARY_PATH`, checks that the venv's torch is the version tch expects (the
//! tch version read from `Cargo.lock`: 0.26 needs torch 2.13, 0.24 torch 2.11), links
//! libtorch's CUDA backend where the libtorch has one (`libtorch_cuda.so`: rustc links with
//! `--as-needed`, and nothing in the crate references a CUDA symbol, so without
//! `--no-as-needed` the library is dropped and the CUDA backend never registers), and
//! compiles the native CPU kernels (`src/ops/native/*.cpp`) against the same libtorch
//! headers (C++17, the ABI torch-sys uses, OpenMP for `at::parallel_for`); on success it sets
//! `cfg(calibconv_native)`, on failure it warns and the crate uses the ATen composition (and the
//! test `native_kernels_are_built` fails unless `CALIBCONV_ALLOW_NO_NATIVE=1`). Linking to
//! libtorch itself comes from torch-sys.

use std::path::PathBuf;

/// The libtorch release each tch release is built for (tch's own table, per minor version).
const TORCH_FOR_TCH: [(&str, &str); 2] = [("0.26", "2.13.0"), ("0.24", "2.11.0")];

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
    let tch = tch_version();
    println!("cargo:rustc-env=CALIBCONV_TCH_VERSION={tch}");
    let Ok(lib) = std::env::var("DEP_TCH_LIBTORCH_LIB") else {
        println!("cargo:rustc-env=CALIBCONV_LIBTORCH_VERSION=unknown");
        println!("cargo:rustc-env=CALIBCONV_CUDA_LINKED=0");
        return;
    };
    let lib = PathBuf::from(&lib);
    let lib = lib.canonicalize().unwrap_or(lib);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    let cuda = lib.join("libtorch_cuda.so").is_file();
    if cuda {
        // Every binary and test executable of the package (rustc-link-arg reaches them all).
        println!(
            "cargo:rustc-link-arg=-Wl,-L{},--no-as-needed,-ltorch_cuda,--as-needed",
            lib.display()
        );
    }
    println!("cargo:rustc-env=CALIBCONV_CUDA_LINKED={}", u8::from(cuda));
    let want = TORCH_FOR_TCH
        .iter()
        .find(|(t, _)| tch.starts_with(&format!("{t}.")))
        .map(|(_, torch)| *torch)
        .unwrap_or_else(|| panic!("calibconv does not know which torch tch {tch} needs"));
    // The pip wheel has no `build-version` file, so torch-sys cannot check it: do it here.
    let version_py = lib.join("..").join("version.py");
    if let Ok(text) = std::fs::read_to_string(&version_py) {
        println!("cargo:rerun-if-changed={}", version_py.display());
        let found = text
            .lines()
            .find_map(|l| l.strip_prefix("__version__ = "))
            .map(|v| v.trim_matches(|c| c == '\'' || c == '"').to_string())
            .unwrap_or_default();
        if !found.starts_with(want) {
            panic!(
                "calibconv needs torch=={want} (tch {tch}), found {found:?} in {}; run `make setup`",
                version_py.display()
            );
        }
        println!("cargo:rustc-env=CALIBCONV_LIBTORCH_VERSION={found}");
    } else {
        println!("cargo:rustc-env=CALIBCONV_LIBTORCH_VERSION={want}");
    }
    compile_native(&lib);
}

/// The version of `tch` in the workspace's `Cargo.lock` (beside the manifest).
fn tch_version() -> String {
    let lock = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets it"))
        .join("Cargo.lock");
    println!("cargo:rerun-if-changed={}", lock.display());
    let text = std::fs::read_to_string(&lock)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", lock.display()));
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        if line.trim() == "name = \"tch\"" {
            if let Some(v) = lines
                .next()
                .and_then(|l| l.trim().strip_prefix("version = "))
            {
                return v.trim_matches('"').to_string();
            }
        }
    }
    panic!("no tch package in {}", lock.display())
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
