//! The two libraries of the float32 products that the few-output-channel kernels do not take
//! (oneDNN, the BLAS) against the ATen composition, in a process of their own: the choice is
//! process-wide, and the library tests compare bits between runs.

use calibconv::ops::{gemm_library, native_available, set_gemm_library, Backend, GemmLibrary};
use tch::{Device, Kind, Tensor};

mod common;
use common::{conv_output_and_gradients as run, max_rel, random_plan3x3};

#[test]
fn both_gemm_libraries_match_the_aten_composition() {
    if !native_available() {
        return; // ops::tests::native_kernels_are_built fails instead
    }
    // The default is the BLAS on every CPU (oneDNN only when asked for).
    assert_eq!(gemm_library(), GemmLibrary::Blas);
    tch::manual_seed(3);
    let opts = (Kind::Float, Device::Cpu);
    // 24 -> 40 channels (no few-output-channel kernels: every product through the library),
    // several tiles.
    let (b, c, co, h, w) = (2, 24, 40, 23, 19);
    let plan = random_plan3x3(h, w, 2.0);
    let x = Tensor::randn([b, c, h, w], opts);
    let wt = Tensor::randn([co, c, 3, 3], opts) * 0.1;
    let bias = Tensor::randn([co], opts);
    let probe = Tensor::randn([b, co, h, w], opts);
    let aten = run(&x, &plan, &wt, &bias, &probe, Backend::Aten);
    let mut libs = vec![GemmLibrary::Blas];
    if tch::utils::has_mkldnn() {
        libs.push(GemmLibrary::OneDnn);
    }
    for lib in libs {
        assert_eq!(set_gemm_library(Some(lib)), lib);
        let got = run(&x, &plan, &wt, &bias, &probe, Backend::Auto);
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
    assert_eq!(set_gemm_library(None), GemmLibrary::Blas);
}
