//! The native CPU kernels against the ATen composition (two independent implementations of the
//! same plan), and the layouts and paths only the native kernels have.

use super::*;

#[test]
fn native_matches_aten_on_random_plans() {
    poison_native_scratch();
    tch::manual_seed(2);
    // (batch, c_in, c_out, h, w, kernel, stride, padding, dilation, groups, per-item offsets,
    // offset scale in pixels: large scales put many samples partly or wholly outside).
    #[rustfmt::skip]
    let cases = [
        (2, 4, 6, 9, 11, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 1.0),
        (3, 6, 4, 8, 7, [3, 3], [2, 1], [0, 2], [1, 2], 2, false, 3.0),
        (2, 8, 8, 10, 6, [3, 5], [1, 2], [2, 1], [2, 1], 4, true, 2.0),
        (1, 5, 3, 12, 12, [1, 1], [1, 1], [0, 0], [1, 1], 1, false, 6.0),
        (2, 3, 5, 6, 9, [3, 3], [1, 1], [1, 1], [1, 1], 1, true, 12.0),
        // 1 and 2 channels: the unrolled gathers of the first layers.
        (2, 1, 3, 7, 5, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        (1, 2, 2, 5, 8, [3, 3], [2, 2], [1, 1], [1, 1], 1, true, 2.0),
        // The vectorised gathers and scatters (8, 16, 32 channels), column tiles that span batch
        // items (B * P above a tile), scatter bands within an item (a tall map, small batch) and
        // tasks of several whole items (small maps). (Their float32 products with 8-1024 outputs
        // run through the few-output-channel kernels; the GEMM library's: the 40- and 72-output
        // cases.)
        (3, 16, 32, 24, 20, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        (2, 8, 8, 40, 36, [3, 3], [1, 1], [1, 1], [1, 1], 1, true, 3.0),
        (5, 32, 16, 12, 10, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 1.5),
        // The few-output-channel kernels (float32, 8 to 1024 outputs): blocks that do not
        // divide the rows, and 4 channels (K*C = 36: the column gradient through the library).
        (2, 8, 16, 33, 17, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        (1, 4, 8, 21, 19, [3, 3], [1, 1], [1, 1], [1, 1], 1, true, 2.0),
        (2, 32, 32, 13, 11, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        // A 1x3 kernel: K*C = 24, below a chunk of the column gradient (its tail paths).
        (2, 8, 16, 9, 10, [1, 3], [1, 1], [0, 1], [1, 1], 1, false, 2.0),
        // 40 outputs: the GEMM library's forward, input and weight gradients (not one of the
        // few-output counts, 8 to 1024; tests/gemm_library.rs runs both libraries).
        (2, 16, 40, 9, 10, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        // A weight with more elements than the whole column matrix (deep layers on small
        // maps): with more than one thread, one GEMM over all rows (see `whole_rows`; 72
        // and 64 outputs through the GEMM library, 24 rows being fewer than a block a thread
        // for the few-output-channel kernels; 64 through those kernels with one thread).
        (2, 64, 72, 3, 4, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        (2, 64, 64, 3, 4, [3, 3], [1, 1], [1, 1], [1, 1], 1, false, 2.0),
        (1, 32, 48, 4, 3, [3, 3], [1, 1], [1, 1], [1, 1], 2, true, 2.0),
    ];
    for (i, &(b, ci, co, h, w, k, s, p, d, g, per_item, scale)) in cases.iter().enumerate() {
        for kind in [Kind::Double, Kind::Float] {
            let opts = (kind, Device::Cpu);
            let ho = (h + 2 * p[0] - d[0] * (k[0] - 1) - 1) / s[0] + 1;
            let wo = (w + 2 * p[1] - d[1] * (k[1] - 1) - 1) / s[1] + 1;
            let taps = k[0] * k[1];
            let off = if per_item {
                Tensor::randn([b, 2 * taps, ho, wo], opts) * scale
            } else {
                Tensor::randn([2 * taps, ho, wo], opts) * scale
            };
            let plan =
                SamplingPlan::new(&off, [h, w], ConvGeometry::new(k, s, p, d), kind).unwrap();
            let x = Tensor::randn([b, ci, h, w], opts);
            let wt = Tensor::randn([co, ci / g, k[0], k[1]], opts);
            let bias = Tensor::randn([co], opts);
            let probe = Tensor::randn([b, co, ho, wo], opts);
            let native = run_backend(&x, &plan, &wt, &bias, g, &probe, Backend::Auto);
            let aten = run_backend(&x, &plan, &wt, &bias, g, &probe, Backend::Aten);
            let tol = if kind == Kind::Double {
                F64_IMPL_TOL
            } else {
                F32_IMPL_TOL
            };
            assert_same(&native, &aten, tol, &format!("case {i} {kind:?}"));
        }
    }
}

#[test]
fn channels_last_and_strided_inputs_keep_their_layout_and_values() {
    tch::manual_seed(3);
    let opts = (Kind::Double, Device::Cpu);
    let Problem {
        plan,
        x,
        w,
        bias,
        probe,
    } = random_problem_in(Kind::Double, [2, 6, 4, 7, 9], 2, 1.5);
    let reference = run_backend(&x, &plan, &w, &bias, 2, &probe, Backend::Aten);
    // Channels-last in: channels-last out and input gradient, like conv2d.
    let cl = run_backend(
        &channels_last(&x),
        &plan,
        &w,
        &bias,
        2,
        &probe,
        Backend::Auto,
    );
    assert!(
        is_channels_last(&cl.out),
        "output strides {:?}",
        cl.out.stride()
    );
    assert!(
        is_channels_last(&cl.input),
        "grad strides {:?}",
        cl.input.stride()
    );
    assert_same(&cl, &reference, F64_IMPL_TOL, "channels-last input");
    // A strided view (every other column of a wider tensor), a channels-last output gradient.
    let wide = Tensor::randn([2, 6, 7, 18], opts);
    let strided = wide.slice(3, 0, 18, 2);
    assert!(!strided.is_contiguous());
    let reference = run_backend(
        &strided.contiguous(),
        &plan,
        &w,
        &bias,
        2,
        &probe,
        Backend::Aten,
    );
    let got = run_backend(
        &strided,
        &plan,
        &w,
        &bias,
        2,
        &channels_last(&probe),
        Backend::Auto,
    );
    assert!(got.out.is_contiguous());
    assert_same(&got, &reference, F64_IMPL_TOL, "strided input");
    // A broadcast (stride-0) output gradient, as from `out.sum()`.
    let x = x.detach().set_requires_grad(true);
    let out = deform_conv2d_planned(&x, &plan, &w, Some(&bias), 2).unwrap();
    let g = Tensor::run_backward(&[out.sum(Kind::Double)], &[&x], false, false);
    let xa = x.detach().set_requires_grad(true);
    let out = deform_conv2d_planned_with(&xa, &plan, &w, Some(&bias), 2, Backend::Aten).unwrap();
    let ga = Tensor::run_backward(&[out.sum(Kind::Double)], &[&xa], false, false);
    assert!(max_rel(&g[0], &ga[0]) < F64_IMPL_TOL);
}

/// NCHW and channels-last inputs differ only in the layout conversions (for float32, 8x8
/// register transposes, element by element at the edges): the outputs and the input and weight
/// gradients must be the same bits, at channel and pixel counts that are and are not multiples
/// of 8. (The bias gradient sums the output gradient in its own layout: rounding only.)
#[test]
fn float32_layout_conversions_are_exact() {
    tch::manual_seed(11);
    for (b, ci, co, h, w) in [
        (2, 8, 16, 8, 8),
        (2, 16, 8, 9, 7),
        (1, 32, 32, 13, 11),
        (3, 12, 20, 6, 10),
        (2, 3, 8, 11, 9),
    ] {
        let p = random_problem([b, ci, co, h, w], 1.5);
        let nchw = run_backend(&p.x, &p.plan, &p.w, &p.bias, 1, &p.probe, Backend::Auto);
        let cl = run_backend(
            &channels_last(&p.x),
            &p.plan,
            &p.w,
            &p.bias,
            1,
            &channels_last(&p.probe),
            Backend::Auto,
        );
        let what = format!("B{b} {ci}->{co} {h}x{w}");
        assert!(
            nchw.out.is_contiguous() && is_channels_last(&cl.out),
            "{what}"
        );
        assert!(nchw.out.equal(&cl.out), "{what}: outputs differ");
        assert!(
            nchw.input.equal(&cl.input),
            "{what}: input gradients differ"
        );
        assert!(
            nchw.weight.equal(&cl.weight),
            "{what}: weight gradients differ"
        );
        assert!(
            max_rel(&nchw.bias, &cl.bias) < 1e-5,
            "{what}: bias gradients"
        );
    }
}

/// The calibrated layer's entry point (`deform_conv2d_planned_as`) returns a channels-last output,
/// or an NCHW one when asked, for NCHW and channels-last inputs alike, with the values and
/// gradients of the plain call: an NCHW image of at most 4 channels (read as it is, the output
/// written channels-last by the kernels; a first layer without input gradient and one with), and
/// wider NCHW inputs (converted first for channels-last, the input gradient coming back NCHW
/// through the conversion); NCHW outputs written by the kernels from either input layout.
#[test]
fn layout_entry_point_matches_the_plain_call() {
    tch::manual_seed(13);
    for (b, ci, co, h, w, input_grad) in [
        (2, 3, 8, 11, 9, false),
        (2, 3, 16, 12, 10, true),
        (1, 4, 8, 7, 9, false),
        (2, 8, 16, 9, 7, true),
    ] {
        let p = random_problem([b, ci, co, h, w], 1.5);
        for x in [p.x.shallow_clone(), channels_last(&p.x)] {
            let what = format!(
                "B{b} {ci}->{co} {h}x{w}, input grad {input_grad}, channels-last input {}",
                is_channels_last(&x)
            );
            let run = |layout: Option<CpuLayout>| {
                let x = x.detach().set_requires_grad(input_grad);
                let (wt, bias) = (
                    p.w.detach().set_requires_grad(true),
                    p.bias.detach().set_requires_grad(true),
                );
                let out = match layout {
                    Some(l) => deform_conv2d_planned_as(&x, &p.plan, &wt, Some(&bias), 1, l),
                    None => deform_conv2d_planned(&x, &p.plan, &wt, Some(&bias), 1),
                }
                .unwrap();
                let loss = (&out * &p.probe).sum(Kind::Float);
                let mut wrt = vec![&wt];
                if input_grad {
                    wrt.push(&x);
                }
                let g = Tensor::run_backward(&[loss], &wrt, false, false);
                (out.detach(), g)
            };
            let (plain, g_plain) = run(None);
            for layout in [CpuLayout::ChannelsLast, CpuLayout::Nchw] {
                let (out, g) = run(Some(layout));
                let what = format!("{what}, {layout:?} output");
                if layout == CpuLayout::ChannelsLast {
                    assert!(is_channels_last(&out), "{what}: output not channels-last");
                } else {
                    assert!(out.is_contiguous(), "{what}: output not NCHW");
                }
                assert!(
                    max_rel(&plain, &out) < F32_IMPL_TOL,
                    "{what}: outputs differ"
                );
                for (name, a, c) in [("weight", &g_plain[0], &g[0])]
                    .into_iter()
                    .chain(input_grad.then(|| ("input", &g_plain[1], &g[1])))
                {
                    assert_eq!(a.size(), c.size(), "{what}: {name} gradient shape");
                    assert!(
                        max_rel(a, c) < F32_IMPL_TOL,
                        "{what}: {name} gradients differ"
                    );
                }
            }
        }
    }
}

/// Offsets that jump by many rows (up, down, alternating) force tall scatter bands and
/// non-monotone row ranges; the input gradient must still be exact.
#[test]
fn input_gradient_is_exact_with_far_reaching_offsets() {
    tch::manual_seed(4);
    let opts = (Kind::Double, Device::Cpu);
    let (h, w) = (24, 5);
    let rows = Tensor::arange(h, opts).view([1, h, 1]);
    // dy = +-(row mod 7) * 1.7, alternating with the row: samples cross many rows both ways.
    let sign = Tensor::from_slice(&[1.0f64, -1.0])
        .repeat([h / 2])
        .view([1, h, 1]);
    let dy = (rows.remainder(7.0) * 1.7 * sign).expand([9, h, w], false);
    let dx = Tensor::randn([9, h, w], opts) * 0.3;
    let off = Tensor::stack(&[dy, dx], 1).reshape([18, h, w]);
    let plan = plan3x3(&off, [h, w], Kind::Double);
    let x = Tensor::randn([2, 3, h, w], opts);
    let (wt, bias) = (Tensor::randn([4, 3, 3, 3], opts), Tensor::randn([4], opts));
    let probe = Tensor::randn([2, 4, h, w], opts);
    let native = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
    let aten = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Aten);
    assert_same(&native, &aten, F64_IMPL_TOL, "far-reaching offsets");
}

#[test]
fn input_rows_no_sample_reads_get_a_zero_gradient() {
    // Every sample within the input's first rows (rows -1 to 2 hold its corners): the rows
    // below are in no band's reach, so no band zeroes their gradient (grad_input_impl zeroes
    // them apart), and it must be exactly zero, with the scratch poisoned.
    poison_native_scratch();
    tch::manual_seed(9);
    let (h, w) = (12, 7);
    for (kind, ci, co, tol) in [
        (Kind::Float, 16, 16, F32_IMPL_TOL),
        (Kind::Double, 3, 4, F64_IMPL_TOL),
    ] {
        let opts = (kind, Device::Cpu);
        let rows = Tensor::arange(h, opts).view([1, h, 1]);
        let dy = (-rows).expand([9, h, w], false) + Tensor::rand([9, h, w], opts) * 0.5;
        let dx = Tensor::randn([9, h, w], opts) * 0.3;
        let off = Tensor::stack(&[dy, dx], 1).reshape([18, h, w]);
        let plan = plan3x3(&off, [h, w], kind);
        let x = Tensor::randn([2, ci, h, w], opts);
        let (wt, bias) = (
            Tensor::randn([co, ci, 3, 3], opts),
            Tensor::randn([co], opts),
        );
        let probe = Tensor::randn([2, co, h, w], opts);
        let native = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
        let aten = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Aten);
        let what = format!("{kind:?} {ci}->{co}, samples in the first rows");
        assert_same(&native, &aten, tol, &what);
        let below = native.input.narrow(2, 3, h - 3);
        assert!(
            below.eq(0.0).all().int64_value(&[]) == 1,
            "{what}: rows no sample reads have a nonzero gradient"
        );
    }
}

/// Finite-difference check in f64 through the native path, with per-item offsets and a
/// channels-last input (the shared-offsets NCHW case is `gradients_match_finite_differences`).
#[test]
fn native_gradients_match_finite_differences_per_item_channels_last() {
    tch::manual_seed(5);
    let opts = (Kind::Double, Device::Cpu);
    let [x, w, b] = random_leaves([&[2, 4, 5, 6], &[6, 2, 3, 3], &[6]], opts);
    let off = Tensor::randn([2, 18, 5, 6], opts) * 2.0;
    let plan = plan3x3(&off, [5, 6], Kind::Double);
    let probe = Tensor::randn([2, 6, 5, 6], opts);
    // The op sees a channels-last input; the variables stay NCHW for perturbing.
    let loss = |x: &Tensor, w: &Tensor, b: &Tensor| -> Tensor {
        let y = deform_conv2d_planned(&channels_last(x), &plan, w, Some(b), 2).unwrap();
        (y * &probe).sum(Kind::Double)
    };
    assert_finite_differences([&x, &w, &b], loss, 5);
}

#[test]
fn native_results_are_deterministic() {
    tch::manual_seed(6);
    let Problem {
        plan,
        x,
        w,
        bias: b,
        probe,
    } = random_problem([3, 16, 16, 40, 40], 2.0);
    let first = run_backend(&x, &plan, &w, &b, 1, &probe, Backend::Auto);
    for _ in 0..3 {
        let again = run_backend(&x, &plan, &w, &b, 1, &probe, Backend::Auto);
        assert!(again.out.equal(&first.out));
        assert!(again.input.equal(&first.input));
        assert!(again.weight.equal(&first.weight));
    }
}

/// C++ exceptions come back as errors, never as aborts: double backward is refused.
#[test]
fn double_backward_is_an_error_not_a_crash() {
    let Problem { plan, x, w, .. } = random_problem_in(Kind::Double, [1, 2, 2, 4, 4], 1, 1.0);
    let (x, w) = (x.set_requires_grad(true), w.set_requires_grad(true));
    let y = deform_conv2d_planned(&x, &plan, &w, None, 1).unwrap();
    let r = Tensor::f_run_backward(&[y.square().sum(Kind::Double)], &[&x], true, true);
    if native_available() {
        let e = r.expect_err("double backward must fail").to_string();
        assert!(e.contains("double backward"), "{e}");
    }
}

#[test]
fn float32_plan_serves_a_float64_input() {
    let opts = (Kind::Double, Device::Cpu);
    let off = Tensor::randn([18, 5, 5], opts);
    let plan32 = plan3x3(&off, [5, 5], Kind::Float);
    let plan64 = plan3x3(&off, [5, 5], Kind::Double);
    let x = Tensor::randn([1, 2, 5, 5], opts);
    let w = Tensor::randn([3, 2, 3, 3], opts);
    let a = deform_conv2d_planned(&x, &plan32, &w, None, 1).unwrap();
    let b = deform_conv2d_planned(&x, &plan64, &w, None, 1).unwrap();
    assert_eq!(a.kind(), Kind::Double);
    // Weights rounded to float32: ~6e-8 relative each.
    assert!(max_rel(&a, &b) < 1e-6);
}

/// Wrap-around plans (panoramas) feed the native kernels unchanged: columns taken modulo `W`,
/// including a 1-wide input whose two horizontal corners are the same pixel.
#[test]
fn native_matches_aten_with_wrap_around() {
    poison_native_scratch();
    tch::manual_seed(7);
    // The gather reads a padded input whose side columns hold the other side's pixels: 3
    // channels (vectors of four), 8 (whole vectors) and 5 (the scalar loop), shared and per-item
    // plans, a one-pixel-wide input.
    for (h, w, c, per_item) in [
        (6, 8, 3, false),
        (5, 1, 3, false),
        (7, 9, 8, true),
        (4, 6, 5, false),
    ] {
        for kind in [Kind::Double, Kind::Float] {
            let opts = (kind, Device::Cpu);
            let off = if per_item {
                Tensor::randn([2, 18, h, w], opts) * 4.0
            } else {
                Tensor::randn([18, h, w], opts) * 4.0
            };
            let plan = plan3x3_with_border(&off, [h, w], kind, Border::WrapX);
            let x = Tensor::randn([2, c, h, w], opts);
            let (wt, bias) = (Tensor::randn([4, c, 3, 3], opts), Tensor::randn([4], opts));
            let probe = Tensor::randn([2, 4, h, w], opts);
            let native = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
            let aten = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Aten);
            let tol = if kind == Kind::Double {
                F64_IMPL_TOL
            } else {
                F32_IMPL_TOL
            };
            assert_same(
                &native,
                &aten,
                tol,
                &format!("wrap-around {h}x{w}, {c} channels, per-item {per_item}, {kind:?}"),
            );
        }
    }
}

#[test]
fn plan_from_offsets_matches_plan_from_their_tensor() {
    use crate::kernel::{compute_offsets, InputFrame, LayerGeometry, OffsetsTensor};
    let camera = crate::camera::shipped("f195");
    let geometry = LayerGeometry {
        kernel: [3, 3],
        stride: [2, 1],
        padding: [1, 1],
        dilation: [1, 2],
    };
    let off = compute_offsets(&camera, [24, 27], &geometry, &InputFrame::default()).unwrap();
    let (s, p, d) = ([2, 1], [1, 1], [1, 2]);
    let direct = SamplingPlan::from_offsets(
        &off,
        ConvGeometry::for_offsets(&off, s, p, d),
        Kind::Float,
        Border::Zeros,
    )
    .unwrap();
    let via = SamplingPlan::new(
        &off.to_tensor(),
        [24, 27],
        ConvGeometry::new([3, 3], s, p, d),
        Kind::Float,
    )
    .unwrap();
    assert!(direct.top_left().equal(via.top_left()) && direct.frac().equal(via.frac()));
    assert!(direct.corner_index().equal(&via.corner_index()) && direct.rows().equal(via.rows()));
    // A geometry the offsets were not computed for is an error, not a wrong plan.
    assert!(SamplingPlan::from_offsets(
        &off,
        ConvGeometry::for_offsets(&off, [1, 1], p, d),
        Kind::Float,
        Border::Zeros
    )
    .is_err());
}

#[test]
fn plan_weights_are_the_bilinear_weights() {
    // A 1x1 kernel on a 4x5 input; output pixel (0, 0) samples (y, x) = (1.25, 2.5): corners
    // (1,2) (1,3) (2,2) (2,3).
    let off = Tensor::zeros([2, 4, 5], (Kind::Double, Device::Cpu));
    let _ = off.get(0).get(0).get(0).fill_(1.25);
    let _ = off.get(1).get(0).get(0).fill_(2.5);
    let plan = SamplingPlan::new(
        &off,
        [4, 5],
        ConvGeometry::new([1, 1], [1, 1], [0, 0], [1, 1]),
        Kind::Double,
    )
    .unwrap();
    let index = plan.corner_index();
    assert_eq!(
        Vec::<i32>::try_from(index.narrow(0, 0, 4)).unwrap(),
        [7, 8, 12, 13]
    );
    let w = plan.f_weights(Kind::Double).unwrap().narrow(0, 0, 4);
    let w = Vec::<f64>::try_from(w).unwrap();
    let expected = [0.75 * 0.5, 0.75 * 0.5, 0.25 * 0.5, 0.25 * 0.5];
    assert!(
        w.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-15),
        "{w:?}"
    );
}

#[test]
fn native_handles_an_empty_batch() {
    if !native_available() {
        return;
    }
    let Problem { plan, x, w, .. } = random_problem([0, 2, 3, 5, 5], 1.0);
    let (x, w) = (x.set_requires_grad(true), w.set_requires_grad(true));
    let y = deform_conv2d_planned(&x, &plan, &w, None, 1).unwrap();
    assert_eq!(y.size(), [0, 3, 5, 5]);
    let g = Tensor::run_backward(&[y.sum(Kind::Float)], &[&x, &w], false, false);
    assert_eq!(g[0].size(), [0, 2, 5, 5]);
    assert_eq!(g[1].abs().sum(Kind::Float).double_value(&[]), 0.0);
}
