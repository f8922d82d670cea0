//! The first-layer and few-output-channel paths of the native kernels against ATen, across
//! instruction-set levels and thread counts; the plan cache.

use super::*;

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
            let run =
                |backend| run_backend_with([&x, &wt0, &bias0], &plan, 1, &probe, backend, false);
            let (a, b_) = (run(Backend::Auto), run(Backend::Aten));
            // The output's layout follows the input's.
            assert!(a.out.is_contiguous(), "NCHW in, NCHW out");
            let cl = deform_conv2d_planned(&channels_last(&x), &plan, &b_.weight, None, 1).unwrap();
            assert!(is_channels_last(&cl), "channels-last in, channels-last out");
            assert_same(
                &a,
                &b_,
                tol,
                &format!("{kind:?} per-item {per_item}, {cout} out"),
            );
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
            let first =
                |backend| run_backend_with([&x, &wt0, &bias0], &plan, 1, &probe, backend, false);
            let (n, a) = (first(Backend::Auto), first(Backend::Aten));
            assert_same(&n, &a, F32_IMPL_TOL, &format!("{what}, first layer"));
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
/// kernels (`SmallKernelIsa::set`) and by those that need it steady to compare two runs bit for
/// bit (tests run in threads of one process).
static SMALL_ISA_CAP: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// The large weights' products through the few-output-channel kernels until dropped (then the
/// CPU's default again); taken under `SMALL_ISA_CAP`, like the level.
struct LargeWeightsFor;

impl LargeWeightsFor {
    fn kernels() -> Self {
        assert_eq!(
            super::LargeWeights::set(Some(super::LargeWeights::Kernels)),
            super::LargeWeights::Kernels
        );
        LargeWeightsFor
    }
}

impl Drop for LargeWeightsFor {
    fn drop(&mut self) {
        super::LargeWeights::set(None);
    }
}

#[test]
fn few_output_channel_kernels_agree_across_isa_levels() {
    if !native_available() {
        return; // native_kernels_are_built fails instead
    }
    let _cap = SMALL_ISA_CAP.lock().unwrap_or_else(|e| e.into_inner());
    poison_native_scratch();
    let top = SmallKernelIsa::current();
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
        let level = SmallKernelIsa::set(Some(SmallKernelIsa::Avx2));
        let avx2 = run_backend(&x, &plan, &wt, &bias, 1, &probe, Backend::Auto);
        SmallKernelIsa::set(Some(SmallKernelIsa::Avx512));
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
    if !native_available() || SmallKernelIsa::current() != SmallKernelIsa::Avx512 {
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
