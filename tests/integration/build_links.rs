//! What the build must contain: libtorch's CUDA backend, linked into the binary wherever the
//! venv's libtorch has it (rustc links with `--as-needed`, and nothing in the crate calls into
//! `libtorch_cuda.so`, so without `build.rs`'s `--no-as-needed` it is silently dropped and
//! `device = "cuda"` can never work).

use std::path::Path;
use std::process::Command;

/// The shared libraries an ELF file names in its dynamic section (`readelf -d`).
fn needed(binary: &Path) -> Vec<String> {
    let out = Command::new("readelf")
        .arg("-d")
        .arg(binary)
        .output()
        .expect("readelf (binutils) runs");
    assert!(out.status.success(), "readelf -d {}", binary.display());
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter(|l| l.contains("(NEEDED)"))
        .filter_map(|l| Some(l.split('[').nth(1)?.trim_end_matches(']').to_string()))
        .collect()
}

#[test]
fn binary_links_the_cuda_backend_when_libtorch_has_one() {
    let bin = Path::new(env!("CARGO_BIN_EXE_calibconv"));
    let libs = needed(bin);
    assert!(
        libs.iter().any(|l| l == "libtorch_cpu.so"),
        "{} does not link libtorch_cpu.so: {libs:?}",
        bin.display()
    );
    let venv_lib = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/libtorch/lib");
    let has_cuda = venv_lib.join("libtorch_cuda.so").is_file();
    let links_cuda = libs.iter().any(|l| l == "libtorch_cuda.so");
    if has_cuda {
        assert!(
            links_cuda,
            "{} has libtorch_cuda.so but {} does not link it: {libs:?}",
            venv_lib.display(),
            bin.display()
        );
    } else {
        assert!(!links_cuda, "no libtorch_cuda.so in {}", venv_lib.display());
    }
}

#[test]
fn info_reports_the_linked_backend() {
    let out = Command::new(env!("CARGO_BIN_EXE_calibconv"))
        .args(["info", "--json"])
        .output()
        .expect("calibconv info runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let venv_lib = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/libtorch/lib");
    let has_cuda = venv_lib.join("libtorch_cuda.so").is_file();
    assert_eq!(
        info["cuda_backend_linked"],
        serde_json::json!(has_cuda),
        "{info}"
    );
    assert_eq!(
        info["cuda_backend_built"],
        serde_json::json!(has_cuda),
        "{info}"
    );
    let dir = info["libtorch_dir"].as_str().expect("libtorch_dir");
    assert!(Path::new(dir).join("libtorch_cpu.so").is_file(), "{dir}");
    assert_eq!(
        info["libtorch_version"]
            .as_str()
            .map(|v| v.starts_with("2.")),
        Some(true)
    );
}
