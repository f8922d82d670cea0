//! Embeds an rpath to libtorch (from torch-sys's `DEP_TCH_LIBTORCH_LIB`) so binaries and tests
//! run without `LD_LIBRARY_PATH`, and checks that the venv's torch is the version tch expects.

use std::path::PathBuf;

const TORCH_VERSION: &str = "2.13.0";

fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
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
}
