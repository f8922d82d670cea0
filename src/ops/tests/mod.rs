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

/// A random 3x3 "same" layer `[B, C_in, C_out, H, W]`, NCHW: its plan (offsets of about `scale`
/// pixels), input, weight, bias and output probe, drawn in that order.
struct Problem {
    plan: SamplingPlan,
    x: Tensor,
    w: Tensor,
    bias: Tensor,
    probe: Tensor,
}

/// A float32 [`Problem`] of one group.
fn random_problem(shape: [i64; 5], scale: f64) -> Problem {
    random_problem_in(Kind::Float, shape, 1, scale)
}

/// A [`Problem`] in `kind` whose weight has `groups` groups.
fn random_problem_in(kind: Kind, [b, ci, co, h, w]: [i64; 5], groups: i64, scale: f64) -> Problem {
    let opts = (kind, Device::Cpu);
    let off = Tensor::randn([18, h, w], opts) * scale;
    Problem {
        plan: plan3x3(&off, [h, w], kind),
        x: Tensor::randn([b, ci, h, w], opts),
        w: Tensor::randn([co, ci / groups, 3, 3], opts),
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

/// [`run_backend_with`] with an input gradient.
fn run_backend(
    x: &Tensor,
    plan: &SamplingPlan,
    w: &Tensor,
    b: &Tensor,
    groups: i64,
    probe: &Tensor,
    backend: Backend,
) -> Grads {
    run_backend_with([x, w, b], plan, groups, probe, backend, true)
}

/// Output and gradients of `(conv(x) * probe).sum()` through `backend` for `[x, w, b]` (input,
/// weight, bias); without `input_grad` the input needs no gradient (a first layer) and
/// `Grads::input` is undefined.
fn run_backend_with(
    [x, w, b]: [&Tensor; 3],
    plan: &SamplingPlan,
    groups: i64,
    probe: &Tensor,
    backend: Backend,
    input_grad: bool,
) -> Grads {
    let x = if input_grad {
        x.detach().set_requires_grad(true)
    } else {
        x.shallow_clone()
    };
    let (w, b) = (
        w.detach().set_requires_grad(true),
        b.detach().set_requires_grad(true),
    );
    let out = deform_conv2d_planned_with(&x, plan, &w, Some(&b), groups, backend).unwrap();
    let loss = (&out * probe).sum(out.kind());
    let leaves = if input_grad {
        vec![&x, &w, &b]
    } else {
        vec![&w, &b]
    };
    let mut g = Tensor::run_backward(&[loss], &leaves, false, false);
    let input = if input_grad {
        g.remove(0)
    } else {
        Tensor::new()
    };
    Grads {
        out: out.detach(),
        input,
        weight: g[0].shallow_clone(),
        bias: g[1].shallow_clone(),
    }
}

/// Asserts that `a` and `b` agree within `tol` (relative), gradient by gradient (an input
/// gradient undefined in both is skipped).
fn assert_same(a: &Grads, b: &Grads, tol: f64, what: &str) {
    for (name, x, y) in [
        ("output", &a.out, &b.out),
        ("grad input", &a.input, &b.input),
        ("grad weight", &a.weight, &b.weight),
        ("grad bias", &a.bias, &b.bias),
    ] {
        if !x.defined() && !y.defined() {
            continue;
        }
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

mod kernels;
mod native;
