//! The two libraries of the float32 products that the few-output-channel kernels do not take
//! (oneDNN, the BLAS) against the ATen composition, in a process of their own: the choice is
//! process-wide, and the library tests compare bits between runs.

use calibconv::ops::{native_available, Backend, GemmLibrary, NativeSetting};

mod common;
use common::{max_rel, Layer3x3};

#[test]
fn both_gemm_libraries_match_the_aten_composition() {
    if !native_available() {
        return; // ops::tests::native_kernels_are_built fails instead
    }
    // The default is the BLAS on every CPU (oneDNN only when asked for).
    assert_eq!(GemmLibrary::current(), GemmLibrary::Blas);
    tch::manual_seed(3);
    // 24 -> 40 channels (no few-output-channel kernels: every product through the library),
    // several tiles.
    let layer = Layer3x3::random([2, 24, 40, 23, 19], 2.0, 0.1);
    let aten = layer.run(Backend::Aten);
    let mut libs = vec![GemmLibrary::Blas];
    if tch::utils::has_mkldnn() {
        libs.push(GemmLibrary::OneDnn);
    }
    for lib in libs {
        assert_eq!(GemmLibrary::set(Some(lib)), lib);
        let got = layer.run(Backend::Auto);
        for (name, g, a) in ["output", "grad input", "grad weight", "grad bias"]
            .iter()
            .zip(&got)
            .zip(&aten)
            .map(|((n, g), a)| (n, g, a))
        {
            let rel = max_rel(g, a);
            assert!(rel < 2e-5, "{lib:?}: {name} differs from ATen by {rel:e}");
        }
    }
    assert_eq!(GemmLibrary::set(None), GemmLibrary::Blas);
}
