use tch::{Device, Kind, Tensor};

use super::*;

/// f32 accumulation over at most a few hundred products: relative error stays far below this.
const F32_TOL: f64 = 1e-5;
/// Central differences in f64 with step 1e-6 on O(1) values: truncation + rounding ~1e-8.
const FD_TOL: f64 = 1e-6;

/// Fills the native kernels' uninitialised scratch buffers with NaN from here on (the whole
/// process: the tests run in threads of one), so that a test holding them to ATen also fails
/// when a pass reads a value it never wrote (fresh pages are zero and would hide that).
fn poison_native_scratch() {
    #[cfg(calibconv_native)]
    super::native::poison_scratch();
}

fn max_rel(a: &Tensor, b: &Tensor) -> f64 {
    let diff = (a - b).abs().max().double_value(&[]);
    let scale = b.abs().max().double_value(&[]).max(1e-12);
    diff / scale
}

/// The plan of a 3x3, stride-1 "same" convolution with offsets `off` on an `hw` input.
fn plan3x3(off: &Tensor, hw: [i64; 2], kind: Kind) -> SamplingPlan {
    plan3x3_with_border(off, hw, kind, Border::Zeros)
}

/// [`plan3x3`] with a choice of border.
fn plan3x3_with_border(off: &Tensor, hw: [i64; 2], kind: Kind, border: Border) -> SamplingPlan {
    SamplingPlan::with_border(
        off,
        hw,
        ConvGeometry::new([3, 3], [1, 1], [1, 1], [1, 1]),
        kind,
        border,
    )
    .unwrap()
}

/// A random float32 3x3 "same" layer `[B, C_in, C_out, H, W]`, NCHW: its plan (offsets of about
/// `scale` pixels), input, weight, bias and output probe, drawn in that order.
struct Problem {
    plan: SamplingPlan,
    x: Tensor,
    w: Tensor,
    bias: Tensor,
    probe: Tensor,
}

fn random_problem([b, ci, co, h, w]: [i64; 5], scale: f64) -> Problem {
    let opts = (Kind::Float, Device::Cpu);
    let off = Tensor::randn([18, h, w], opts) * scale;
    Problem {
        plan: plan3x3(&off, [h, w], Kind::Float),
        x: Tensor::randn([b, ci, h, w], opts),
        w: Tensor::randn([co, ci, 3, 3], opts),
        bias: Tensor::randn([co], opts),
        probe: Tensor::randn([b, co, h, w], opts),
    }
}

/// Standard-normal tensors of these shapes that require gradients (input, weight, bias).
fn random_leaves(shapes: [&[i64]; 3], opts: (Kind, Device)) -> [Tensor; 3] {
    shapes.map(|shape| Tensor::randn(shape, opts).set_requires_grad(true))
}

/// Central finite differences (step 1e-6, every `stride`-th element of each variable) against
/// autograd's gradient of `loss` at `vars` (input, weight, bias), to [`FD_TOL`].
fn assert_finite_differences(
    vars: [&Tensor; 3],
    loss: impl Fn(&Tensor, &Tensor, &Tensor) -> Tensor,
    stride: usize,
) {
    let grads = Tensor::run_backward(&[loss(vars[0], vars[1], vars[2])], &vars, false, false);
    let eps = 1e-6;
    for (which, g) in grads.iter().enumerate() {
        for e in (0..g.numel() as i64).step_by(stride) {
            let fd = tch::no_grad(|| {
                let v = vars.map(|t| t.detach().copy());
                let flat = v[which].view(-1);
                let v0 = flat.double_value(&[e]);
                let _ = flat.get(e).fill_(v0 + eps);
                let up = loss(&v[0], &v[1], &v[2]).double_value(&[]);
                let _ = flat.get(e).fill_(v0 - eps);
                let down = loss(&v[0], &v[1], &v[2]).double_value(&[]);
                (up - down) / (2.0 * eps)
            });
            let an = g.reshape(-1).double_value(&[e]);
            assert!(
                (fd - an).abs() < FD_TOL * (1.0 + an.abs()),
                "param {which} elem {e}: fd {fd} vs autograd {an}"
            );
        }
    }
}

#[test]
fn zero_offsets_equal_conv2d() {
    tch::manual_seed(0);
    for (stride, padding, dilation, groups) in [
        ([1, 1], [1, 1], [1, 1], 1),
        ([2, 1], [0, 2], [1, 2], 2),
        ([2, 2], [1, 1], [2, 2], 4),
    ] {
        let x = Tensor::randn([2, 4, 9, 11], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([8, 4 / groups, 3, 3], (Kind::Float, Device::Cpu));
        let b = Tensor::randn([8], (Kind::Float, Device::Cpu));
        let reference = x.conv2d(&w, Some(&b), stride, padding, dilation, groups);
        let (_, _, ho, wo) = reference.size4().unwrap();
        let zeros = Tensor::zeros([18, ho, wo], (Kind::Float, Device::Cpu));
        let got = deform_conv2d(&x, &zeros, &w, Some(&b), stride, padding, dilation, groups);
        assert!(
            max_rel(&got, &reference) < F32_TOL,
            "stride {stride:?} groups {groups}"
        );
    }
}

#[test]
fn integer_offsets_shift_the_input() {
    // Every tap shifted by (+1, -1) equals conv2d of the input shifted the same way.
    let x = Tensor::randn([1, 2, 8, 8], (Kind::Double, Device::Cpu));
    let w = Tensor::randn([3, 2, 3, 3], (Kind::Double, Device::Cpu));
    let off = Tensor::stack(
        &[
            Tensor::ones([6, 6], (Kind::Double, Device::Cpu)),
            -Tensor::ones([6, 6], (Kind::Double, Device::Cpu)),
        ],
        0,
    )
    .repeat([9, 1, 1]);
    let got = deform_conv2d(&x, &off, &w, None, [1, 1], [0, 0], [1, 1], 1);
    // Sample (y + 1, x - 1): pad one column on the left, drop the first row.
    let shifted = x
        .pad([1, 0, 0, 1], "constant", Some(0.0))
        .narrow(2, 1, 8)
        .narrow(3, 0, 8);
    let reference = shifted.conv2d(&w, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1);
    assert!(max_rel(&got, &reference) < 1e-12);
}

#[test]
fn per_item_offsets_match_shared_offsets() {
    let x = Tensor::randn([3, 2, 7, 6], (Kind::Float, Device::Cpu));
    let w = Tensor::randn([4, 2, 3, 3], (Kind::Float, Device::Cpu));
    let off = Tensor::randn([18, 7, 6], (Kind::Float, Device::Cpu)) * 1.5;
    let shared = deform_conv2d(&x, &off, &w, None, [1, 1], [1, 1], [1, 1], 1);
    let per_item = deform_conv2d(
        &x,
        &off.unsqueeze(0).repeat([3, 1, 1, 1]),
        &w,
        None,
        [1, 1],
        [1, 1],
        [1, 1],
        1,
    );
    assert!(max_rel(&per_item, &shared) < F32_TOL);
    // Different offsets per item: item 1 alone must match a batch-of-one call.
    let offs = Tensor::randn([3, 18, 7, 6], (Kind::Float, Device::Cpu));
    let all = deform_conv2d(&x, &offs, &w, None, [1, 1], [1, 1], [1, 1], 1);
    let one = deform_conv2d(
        &x.narrow(0, 1, 1),
        &offs.get(1),
        &w,
        None,
        [1, 1],
        [1, 1],
        [1, 1],
        1,
    );
    assert!(max_rel(&all.narrow(0, 1, 1), &one) < F32_TOL);
}

/// Finite-difference gradient check in f64 for input, weight and bias.
#[test]
fn gradients_match_finite_differences() {
    tch::manual_seed(1);
    let opts = (Kind::Double, Device::Cpu);
    let [x, w, b] = random_leaves([&[2, 4, 5, 6], &[4, 2, 3, 3], &[4]], opts);
    // Fractional offsets, some pointing outside the map.
    let off = Tensor::randn([18, 3, 2], opts) * 2.0;
    let probe = Tensor::randn([2, 4, 3, 2], opts);
    let loss = |x: &Tensor, w: &Tensor, b: &Tensor| -> Tensor {
        (deform_conv2d(x, &off, w, Some(b), [2, 2], [1, 1], [1, 2], 2) * &probe).sum(Kind::Double)
    };
    assert_finite_differences([&x, &w, &b], loss, 7);
}

#[test]
fn bad_shapes_are_clear_errors() {
    let x = Tensor::zeros([1, 4, 8, 8], (Kind::Float, Device::Cpu));
    let w = Tensor::zeros([4, 4, 3, 3], (Kind::Float, Device::Cpu));
    let wrong = Tensor::zeros([18, 7, 8], (Kind::Float, Device::Cpu));
    let e = f_deform_conv2d(&x, &wrong, &w, None, [1, 1], [1, 1], [1, 1], 1).unwrap_err();
    assert!(e.to_string().contains("[18, 8, 8]"), "{e}");
    let off = Tensor::zeros([18, 8, 8], (Kind::Float, Device::Cpu));
    let e = f_deform_conv2d(&x, &off, &w, None, [1, 1], [1, 1], [1, 1], 3).unwrap_err();
    assert!(e.to_string().contains("groups"), "{e}");
    let e = f_deform_conv2d(
        &x.to_kind(Kind::Int),
        &off,
        &w,
        None,
        [1, 1],
        [1, 1],
        [1, 1],
        1,
    )
    .unwrap_err();
    assert!(e.to_string().contains("float32"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// The native CPU kernels against the ATen composition (two independent implementations of the
// same plan), and the layouts and paths only the native kernels have.

/// Float64 runs of the two implementations differ by summation order only: ~1e-15 relative.
const F64_IMPL_TOL: f64 = 1e-12;
/// Float32 runs: sums of up to ~500 products, different order: ~1e-6 relative at worst.
const F32_IMPL_TOL: f64 = 2e-5;

/// Output and gradients (input, weight, bias) of `(conv(x) * probe).sum()`.
struct Grads {
    out: Tensor,
    input: Tensor,
    weight: Tensor,
    bias: Tensor,
}

#[allow(clippy::too_many_arguments)]
fn run_backend(
    x: &Tensor,
    plan: &SamplingPlan,
    w: &Tensor,
    b: &Tensor,
    groups: i64,
    probe: &Tensor,
    backend: Backend,
) -> Grads {
    let (x, w, b) = (
        x.detach().set_requires_grad(true),
        w.detach().set_requires_grad(true),
        b.detach().set_requires_grad(true),
    );
    let out = deform_conv2d_planned_with(&x, plan, &w, Some(&b), groups, backend).unwrap();
    let loss = (&out * probe).sum(out.kind());
    let g = Tensor::run_backward(&[loss], &[&x, &w, &b], false, false);
    Grads {
        out: out.detach(),
        input: g[0].shallow_clone(),
        weight: g[1].shallow_clone(),
        bias: g[2].shallow_clone(),
    }
}

fn assert_same(a: &Grads, b: &Grads, tol: f64, what: &str) {
    for (name, x, y) in [
        ("output", &a.out, &b.out),
        ("grad input", &a.input, &b.input),
        ("grad weight", &a.weight, &b.weight),
        ("grad bias", &a.bias, &b.bias),
    ] {
        assert_eq!(x.size(), y.size(), "{what}: {name} shape");
        let rel = max_rel(x, y);
        assert!(
            rel < tol,
            "{what}: {name} differs by {rel:e} (tolerance {tol:e})"
        );
    }
}

/// A channels-last copy of an NCHW tensor (same values, NHWC memory).
fn channels_last(x: &Tensor) -> Tensor {
    x.permute([0, 2, 3, 1]).contiguous().permute([0, 3, 1, 2])
}

fn is_channels_last(x: &Tensor) -> bool {
    let (_, c, h, w) = x.size4().unwrap();
    x.stride() == [h * w * c, 1, w * c, c]
}

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
    let off = Tensor::randn([18, 7, 9], opts) * 1.5;
    let plan = plan3x3(&off, [7, 9], Kind::Double);
    let x = Tensor::randn([2, 6, 7, 9], opts);
    let (w, bias) = (Tensor::randn([4, 3, 3, 3], opts), Tensor::randn([4], opts));
    let probe = Tensor::randn([2, 4, 7, 9], opts);
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
    let opts = (Kind::Float, Device::Cpu);
    let off = Tensor::randn([18, 40, 40], opts) * 2.0;
    let plan = plan3x3(&off, [40, 40], Kind::Float);
    let x = Tensor::randn([3, 16, 40, 40], opts);
    let (w, b) = (
        Tensor::randn([16, 16, 3, 3], opts),
        Tensor::randn([16], opts),
    );
    let probe = Tensor::randn([3, 16, 40, 40], opts);
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
    let opts = (Kind::Double, Device::Cpu);
    let off = Tensor::randn([18, 4, 4], opts);
    let plan = plan3x3(&off, [4, 4], Kind::Double);
    let x = Tensor::randn([1, 2, 4, 4], opts).set_requires_grad(true);
    let w = Tensor::randn([2, 2, 3, 3], opts).set_requires_grad(true);
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
    let opts = (Kind::Float, Device::Cpu);
    let off = Tensor::randn([18, 5, 5], opts);
    let plan = plan3x3(&off, [5, 5], Kind::Float);
    let x = Tensor::randn([0, 2, 5, 5], opts).set_requires_grad(true);
    let w = Tensor::randn([3, 2, 3, 3], opts).set_requires_grad(true);
    let y = deform_conv2d_planned(&x, &plan, &w, None, 1).unwrap();
    assert_eq!(y.size(), [0, 3, 5, 5]);
    let g = Tensor::run_backward(&[y.sum(Kind::Float)], &[&x, &w], false, false);
    assert_eq!(g[0].size(), [0, 2, 5, 5]);
    assert_eq!(g[1].abs().sum(Kind::Float).double_value(&[]), 0.0);
}

/// CI runs with the native kernels: without them every native-vs-ATen test above compares the
/// ATen composition with itself and passes vacuously. A build that cannot have them (no C++17
/// compiler) says so explicitly with `CALIBCONV_ALLOW_NO_NATIVE=1`.
#[test]
fn native_kernels_are_built() {
    if std::env::var("CALIBCONV_ALLOW_NO_NATIVE").as_deref() == Ok("1") {
        return;
    }
    assert!(
        native_available(),
        "the native CPU kernels were not built (see build.rs's warning); set \
         CALIBCONV_ALLOW_NO_NATIVE=1 to run the tests on the ATen composition alone"
    );
}

/// A first layer: the input (an image) needs no gradient, so the native forward keeps its few-
/// channel column matrix for the weight gradient instead of gathering it again. Output, weight
/// and bias gradients still match the ATen composition, shared and per-item offsets, over tiles
/// that span batch items.
#[test]
fn first_layer_without_input_gradient_matches_aten() {
    poison_native_scratch();
    tch::manual_seed(5);
    for (kind, tol) in [(Kind::Double, F64_IMPL_TOL), (Kind::Float, F32_IMPL_TOL)] {
        // 8 and 16 output channels (the few-output-channel kernels), and 40 (the weight
        // gradient through the GEMM library).
        for (per_item, cout) in [(false, 8), (true, 8), (false, 16), (false, 40)] {
            let opts = (kind, Device::Cpu);
            let (b, c, h, w) = (3, 3, 30, 26);
            let off = if per_item {
                Tensor::randn([b, 18, h, w], opts) * 2.0
            } else {
                Tensor::randn([18, h, w], opts) * 2.0
            };
            let plan = plan3x3(&off, [h, w], kind);
            let x = Tensor::randn([b, c, h, w], opts);
            let probe = Tensor::randn([b, cout, h, w], opts);
            // Drawn once: re-seeding the global generator before each run would race with the
            // other tests' draws (they run in parallel threads of one process).
            let (wt0, bias0) = (
                Tensor::randn([cout, c, 3, 3], opts),
                Tensor::randn([cout], opts),
            );
            let run = |backend| {
                let wt = wt0.detach().set_requires_grad(true);
                let bias = bias0.detach().set_requires_grad(true);
                let out =
                    deform_conv2d_planned_with(&x, &plan, &wt, Some(&bias), 1, backend).unwrap();
                let loss = (&out * &probe).sum(kind);
                let g = Tensor::run_backward(&[loss], &[&wt, &bias], false, false);
                (out.detach(), g[0].shallow_clone(), g[1].shallow_clone())
            };
            let (a, b_) = (run(Backend::Auto), run(Backend::Aten));
            // The output's layout follows the input's.
            assert!(a.0.is_contiguous(), "NCHW in, NCHW out");
            let cl = deform_conv2d_planned(&channels_last(&x), &plan, &b_.1, None, 1).unwrap();
            assert!(is_channels_last(&cl), "channels-last in, channels-last out");
            for (name, x, y) in [
                ("output", &a.0, &b_.0),
                ("grad weight", &a.1, &b_.1),
                ("grad bias", &a.2, &b_.2),
            ] {
                let rel = max_rel(x, y);
                assert!(
                    rel < tol,
                    "{kind:?} per-item {per_item}, {cout} out: {name} differs by {rel:e}"
                );
            }
        }
    }
}

/// Three float channels with one plan for the batch are gathered for every item at once (a padded
/// copy holding each pixel's items side by side, four to a vector), and as a first layer their
/// weight gradient gathers the columns again by pixel blocks of all items instead of keeping
/// them (from four items on): outputs and gradients match the ATen composition for batches that
/// fill the last vector of four items wholly or partly (4, 5, 7), both borders, both input
/// layouts, with and without an input gradient.
#[test]
fn three_channel_batches_match_aten() {
    poison_native_scratch();
    tch::manual_seed(23);
    let opts = (Kind::Float, Device::Cpu);
    for (b, cout, h, w, border) in [
        (4, 8, 9, 11, Border::Zeros),
        (4, 16, 7, 6, Border::WrapX),
        (5, 8, 10, 9, Border::Zeros),
        (7, 16, 6, 13, Border::WrapX),
    ] {
        let off = Tensor::randn([18, h, w], opts) * 3.0;
        let plan = plan3x3_with_border(&off, [h, w], Kind::Float, border);
        let x0 = Tensor::randn([b, 3, h, w], opts);
        let (wt0, bias0) = (
            Tensor::randn([cout, 3, 3, 3], opts),
            Tensor::randn([cout], opts),
        );
        let probe = Tensor::randn([b, cout, h, w], opts);
        for x in [x0.shallow_clone(), channels_last(&x0)] {
            let what = format!(
                "B{b} 3->{cout} {h}x{w} {border:?}, channels-last {}",
                is_channels_last(&x)
            );
            // with an input gradient
            let native = run_backend(&x, &plan, &wt0, &bias0, 1, &probe, Backend::Auto);
            let aten = run_backend(&x, &plan, &wt0, &bias0, 1, &probe, Backend::Aten);
            assert_same(&native, &aten, F32_IMPL_TOL, &what);
            // a first layer: the weight and bias gradients only
            let first = |backend| {
                let wt = wt0.detach().set_requires_grad(true);
                let bias = bias0.detach().set_requires_grad(true);
                let out =
                    deform_conv2d_planned_with(&x, &plan, &wt, Some(&bias), 1, backend).unwrap();
                let loss = (&out * &probe).sum(Kind::Float);
                let g = Tensor::run_backward(&[loss], &[&wt, &bias], false, false);
                [out.detach(), g[0].shallow_clone(), g[1].shallow_clone()]
            };
            let (n, a) = (first(Backend::Auto), first(Backend::Aten));
            for (name, u, v) in [
                ("output", &n[0], &a[0]),
                ("grad weight", &n[1], &a[1]),
                ("grad bias", &n[2], &a[2]),
            ] {
                let rel = max_rel(u, v);
                assert!(
                    rel < F32_IMPL_TOL,
                    "{what}, first layer: {name} differs by {rel:e}"
                );
            }
        }
    }
}

/// A plan shared by the batch and per-item plans with the same offsets for every item must give
/// the same bits (outputs, and the weight gradient of a first layer, computed from the columns
/// its forward pass kept or, for 3 channels from four items on, gathered again by pixel blocks
/// of all items), in and out of grad mode (without it a first layer keeps no columns).
/// Three channels are gathered as vectors of four; an offset places a corner on the batch's last
/// pixel (read from a padded copy) and the odd sizes leave partial stages.
#[test]
fn shared_and_per_item_plans_give_the_same_bits() {
    if !native_available() {
        return; // native_kernels_are_built fails instead
    }
    tch::manual_seed(17);
    let opts = (Kind::Float, Device::Cpu);
    for (b, c, cout, h, w) in [
        (3, 3, 8, 11, 9),
        (2, 3, 16, 7, 13),
        // from four items on, three channels go through the batch gather with one plan and its
        // weight gradient by pixel blocks: per-item plans take the same order
        (5, 3, 16, 7, 13),
        (3, 4, 8, 9, 9),
        (3, 8, 16, 10, 7),
        (2, 16, 8, 6, 11),
    ] {
        let off = Tensor::randn([18, h, w], opts) * 3.0;
        // The last output pixel's centre tap samples a quarter pixel past the last input pixel.
        let _ = off
            .narrow(0, 8, 2)
            .narrow(1, h - 1, 1)
            .narrow(2, w - 1, 1)
            .fill_(0.25);
        let shared = plan3x3(&off, [h, w], Kind::Float);
        let per_item = plan3x3(&off.unsqueeze(0).repeat([b, 1, 1, 1]), [h, w], Kind::Float);
        let x = Tensor::randn([b, c, h, w], opts);
        let (wt0, bias0) = (
            Tensor::randn([cout, c, 3, 3], opts),
            Tensor::randn([cout], opts),
        );
        let probe = Tensor::randn([b, cout, h, w], opts);
        for x in [x.shallow_clone(), channels_last(&x)] {
            // (a first layer: the input needs no gradient, the forward pass keeps its columns but
            // for 3 channels and >= 4 items)
            let run = |plan: &SamplingPlan| {
                let wt = wt0.detach().set_requires_grad(true);
                let bias = bias0.detach().set_requires_grad(true);
                let out = deform_conv2d_planned(&x, plan, &wt, Some(&bias), 1).unwrap();
                let loss = (&out * &probe).sum(Kind::Float);
                let g = Tensor::run_backward(&[loss], &[&wt], false, false);
                let eval = tch::no_grad(|| deform_conv2d_planned(&x, plan, &wt, Some(&bias), 1));
                (out.detach(), g[0].shallow_clone(), eval.unwrap())
            };
            let (a, p) = (run(&shared), run(&per_item));
            let what = format!(
                "B{b} {c}->{cout} {h}x{w}, channels-last {}",
                is_channels_last(&x)
            );
            assert!(a.0.equal(&p.0), "{what}: outputs differ");
            assert!(a.1.equal(&p.1), "{what}: weight gradients differ");
            assert!(a.2.equal(&p.2), "{what}: outputs without grad mode differ");
        }
    }
}

/// The few-output-channel kernels are compiled per instruction-set level with different register
/// blocking (AVX-512 for 8-1024 outputs, AVX2 for 8-32): where both levels have kernels they
/// give bit-identical results (the same fused multiply-adds in the same order per element); every
/// level's path (at AVX2, 64-1024 outputs go through the GEMM library) matches the ATen
/// composition, for 8, 16, 32, 64, 128, 256, 512 and 1024 outputs and row counts that leave
/// partial blocks, and for weights above SMALL_LARGE_WEIGHT (blocks of 256 rows, gathered and
/// multiplied in slabs of 512 columns: 64->512 on 552 pixels is two blocks and a part, K*C = 576
/// a slab and a part; at 96->512 the first slab ends inside tap 5's channels). On a CPU without
/// AVX-512 the AVX2 path is still held to ATen.
/// Held by the tests that move the process-wide instruction-set cap of the few-output-channel
/// kernels (`cap_small_kernel_isa`) and by those that need it steady to compare two runs bit for
/// bit (tests run in threads of one process).
static SMALL_ISA_CAP: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// The large weights' products through the few-output-channel kernels until dropped (then the
/// CPU's default again); taken under `SMALL_ISA_CAP`, like the level.
struct LargeWeightsFor;

impl LargeWeightsFor {
    fn kernels() -> Self {
        assert_eq!(
            super::set_large_weights(Some(super::LargeWeights::Kernels)),
            super::LargeWeights::Kernels
        );
        LargeWeightsFor
    }
}

impl Drop for LargeWeightsFor {
    fn drop(&mut self) {
        super::set_large_weights(None);
    }
}

#[test]
fn few_output_channel_kernels_agree_across_isa_levels() {
    if !native_available() {
        return; // native_kernels_are_built fails instead
    }
    let _cap = SMALL_ISA_CAP.lock().unwrap_or_else(|e| e.into_inner());
    poison_native_scratch();
    let top = small_kernel_isa();
    tch::manual_seed(8);
    for (b, ci, co, h, w) in [
        (2, 8, 8, 11, 13),
        (3, 16, 16, 9, 7),
        (2, 16, 32, 10, 9),
        (2, 32, 64, 7, 9),
        (1, 16, 128, 12, 13),
        (1, 8, 256, 17, 16),
        (1, 8, 512, 24, 23),
        (1, 64, 512, 24, 23),
        (1, 96, 512, 24, 23),
        (1, 32, 1024, 33, 32),
        // the 128- and 256-channel gathers and scatters in 64-byte vectors (AVX-512; the same
        // bits as the general loop of the AVX2 level, checked below), and large weights of 256
        // and 512 channels in (slabs)
        (2, 128, 16, 9, 8),
        (1, 256, 32, 6, 7),
        (1, 256, 128, 9, 8),
        (1, 512, 64, 5, 6),
        // fewer pixels than outputs and a large weight: with more than one thread the first
        // goes through the GEMM library whole (`whole_rows`), the second (256 rows a thread at
        // two threads) through these kernels on every thread
        (1, 128, 512, 6, 5),
        (2, 32, 1024, 16, 16),
    ] {
        let Problem {
            plan,
            x,
            w: wt,
            bias,
            probe,
        } = random_problem([b, ci, co, h, w], 2.0);
        let at_top = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
        let level = cap_small_kernel_isa(SmallKernelIsa::Avx2);
        let avx2 = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
        cap_small_kernel_isa(SmallKernelIsa::Avx512);
        let aten = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Aten);
        let what = format!("{ci}->{co}, {b}x{h}x{w}");
        assert_same(
            &avx2,
            &aten,
            F32_IMPL_TOL,
            &format!("{what}, {level:?} vs ATen"),
        );
        assert_same(
            &at_top,
            &aten,
            F32_IMPL_TOL,
            &format!("{what}, {top:?} vs ATen"),
        );
        if top == SmallKernelIsa::Avx512 {
            assert_eq!(level, SmallKernelIsa::Avx2, "the cap must take effect");
        }
        if top == SmallKernelIsa::Avx512 && co <= 32 {
            for (name, a, c) in [
                ("output", &at_top.out, &avx2.out),
                ("grad input", &at_top.input, &avx2.input),
                ("grad weight", &at_top.weight, &avx2.weight),
            ] {
                assert!(
                    a.equal(c),
                    "{what}: {name}: AVX-512 and AVX2 kernels differ"
                );
            }
        }
    }
}

/// With several threads the few-output-channel kernels split the weight gradient of a large
/// weight by output panels, each thread summing all rows in their order: the gradients (and the
/// output) are those of one thread, bit for bit. (The bias gradient is ATen's sum, not held to
/// it.) The kernels are asked for: on Intel CPUs with MKL the BLAS takes these products by
/// default, whose sums depend on its threads.
#[test]
fn large_weight_gradients_do_not_depend_on_the_thread_count() {
    let _cap = SMALL_ISA_CAP.lock().unwrap_or_else(|e| e.into_inner());
    if !native_available() || small_kernel_isa() != SmallKernelIsa::Avx512 {
        return; // (the 256- and 512-output kernels are AVX-512's)
    }
    let _kernels = LargeWeightsFor::kernels();
    poison_native_scratch();
    tch::manual_seed(9);
    let threads = tch::get_num_threads();
    // (large weights, at least 256 rows a thread at two threads; the last would go through the
    // GEMM library whole, `whole_rows`, with fewer)
    for shape in [
        [2, 128, 256, 16, 16],
        [1, 64, 512, 24, 24],
        [2, 32, 1024, 16, 16],
    ] {
        let Problem {
            plan,
            x,
            w,
            bias,
            probe,
        } = random_problem(shape, 2.0);
        tch::set_num_threads(1);
        let one = run_backend(&x, &plan, &w, &bias, 1, &probe, Backend::Auto);
        tch::set_num_threads(2);
        let two = run_backend(&x, &plan, &w, &bias, 1, &probe, Backend::Auto);
        tch::set_num_threads(threads);
        for (name, a, b) in [
            ("output", &one.out, &two.out),
            ("grad input", &one.input, &two.input),
            ("grad weight", &one.weight, &two.weight),
        ] {
            assert!(a.equal(b), "{shape:?}: {name}: one and two threads differ");
        }
    }
}

/// The functional op's plan cache: the same offsets tensor reuses its plan (same storage); an
/// in-place change of the offsets (a new version) gets a new plan, and the result follows it.
#[test]
fn functional_plans_are_cached_by_tensor_identity_and_version() {
    tch::manual_seed(7);
    let opts = (Kind::Float, Device::Cpu);
    let mut off = Tensor::randn([18, 6, 7], opts);
    let plan = |off: &Tensor| {
        super::tensor_plan(
            off,
            [6, 7],
            ConvGeometry::new([3, 3], [1, 1], [1, 1], [1, 1]),
            Kind::Float,
            Device::Cpu,
        )
        .unwrap()
    };
    let (a, b) = (plan(&off), plan(&off));
    assert!(a.shares_storage_with(&b), "second call must hit the cache");
    let x = Tensor::randn([2, 4, 6, 7], opts);
    let w = Tensor::randn([5, 4, 3, 3], opts);
    let before = deform_conv2d(&x, &off, &w, None, [1, 1], [1, 1], [1, 1], 1);
    let _ = off.g_add_scalar_(0.5);
    let c = plan(&off);
    assert!(
        !a.shares_storage_with(&c),
        "an in-place change must build a new plan"
    );
    let after = deform_conv2d(&x, &off, &w, None, [1, 1], [1, 1], [1, 1], 1);
    let fresh = deform_conv2d(&x, &off.copy(), &w, None, [1, 1], [1, 1], [1, 1], 1);
    assert!(
        max_rel(&after, &fresh) < 1e-6,
        "stale plan after an in-place change"
    );
    assert!(
        max_rel(&after, &before) > 1e-3,
        "the change must show in the result"
    );
}
