//! The two libraries of the large weights' products (the few-output-channel kernels, the BLAS)
//! against the ATen composition, in a process of their own: the choice is process-wide.

use calibconv::ops::{native_available, Backend, LargeWeights, NativeSetting, SmallKernelIsa};

mod common;
use common::{max_rel, Layer3x3};

const NAMES: [&str; 4] = ["output", "grad input", "grad weight", "grad bias"];

#[test]
fn both_libraries_of_large_weights_match_aten_and_split_where_documented() {
    if !native_available() || SmallKernelIsa::current() != SmallKernelIsa::Avx512 {
        // The choice exists only where the kernels take 512 and 1024 outputs (AVX-512).
        return;
    }
    // One thread: with more, layers this small (510 rows) go through the BLAS's threaded products
    // whatever the choice (whole_rows in deform.cpp).
    tch::set_num_threads(1);
    tch::manual_seed(5);
    let b = 2;
    // 64 -> 512: a weight of 576 x 512 values (1.1 MiB), every product through the kernels
    // whatever the choice (the BLAS takes weights over 4 MiB); 128 -> 1024: 4.5 MiB, every
    // product chosen on 2 x 17 x 15 = 510 output pixels, the gradients only on 2 x 24 x 24 = 1152
    // (a forward of 1024 rows or more stays with the kernels).
    for (c, co, (h, w), forward_chosen, gradients_chosen) in [
        (64, 512, (17, 15), false, false),
        (128, 1024, (17, 15), true, true),
        (128, 1024, (24, 24), false, true),
    ] {
        let layer = Layer3x3::random([b, c, co, h, w], 2.0, 0.05);
        let aten = layer.run(Backend::Aten);
        let mut by_lib = Vec::new();
        for lib in [LargeWeights::Kernels, LargeWeights::Blas] {
            assert_eq!(LargeWeights::set(Some(lib)), lib);
            let got = layer.run(Backend::Auto);
            for ((name, g), a) in NAMES.iter().zip(&got).zip(&aten) {
                let rel = max_rel(g, a);
                assert!(
                    rel < 2e-5,
                    "{c}->{co} {h}x{w} {lib:?}: {name} differs from ATen by {rel:e}"
                );
            }
            by_lib.push(got);
        }
        // The switch took effect where documented: above 4 MiB the gradients of the input and the
        // weight come from other products (other rounding), the output only on few rows.
        let same = |i: usize| by_lib[0][i].equal(&by_lib[1][i]);
        assert_eq!(!same(0), forward_chosen, "{c}->{co} {h}x{w}: output");
        assert_eq!(!same(1), gradients_chosen, "{c}->{co} {h}x{w}: grad input");
        assert_eq!(!same(2), gradients_chosen, "{c}->{co} {h}x{w}: grad weight");
    }
    LargeWeights::set(None);
}
