use tch::{Device, Kind, Tensor};

use super::*;

/// f32 accumulation over at most a few hundred products: relative error stays far below this.
const F32_TOL: f64 = 1e-5;
/// Central differences in f64 with step 1e-6 on O(1) values: truncation + rounding ~1e-8.
const FD_TOL: f64 = 1e-6;

fn max_rel(a: &Tensor, b: &Tensor) -> f64 {
    let diff = (a - b).abs().max().double_value(&[]);
    let scale = b.abs().max().double_value(&[]).max(1e-12);
    diff / scale
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
    let x = Tensor::randn([2, 4, 5, 6], opts).set_requires_grad(true);
    let w = Tensor::randn([4, 2, 3, 3], opts).set_requires_grad(true);
    let b = Tensor::randn([4], opts).set_requires_grad(true);
    // Fractional offsets, some pointing outside the map.
    let off = Tensor::randn([18, 3, 2], opts) * 2.0;
    let probe = Tensor::randn([2, 4, 3, 2], opts);
    let loss = |x: &Tensor, w: &Tensor, b: &Tensor| -> Tensor {
        (deform_conv2d(x, &off, w, Some(b), [2, 2], [1, 1], [1, 2], 2) * &probe).sum(Kind::Double)
    };
    let l = loss(&x, &w, &b);
    let grads = Tensor::run_backward(&[l], &[&x, &w, &b], false, false);
    let eps = 1e-6;
    for (which, g) in grads.iter().enumerate() {
        let n = g.numel();
        for e in (0..n).step_by(7) {
            let fd = tch::no_grad(|| {
                let vars = [x.detach().copy(), w.detach().copy(), b.detach().copy()];
                let flat = vars[which].view(-1);
                let v0 = flat.double_value(&[e as i64]);
                let _ = flat.get(e as i64).fill_(v0 + eps);
                let up = loss(&vars[0], &vars[1], &vars[2]).double_value(&[]);
                let _ = vars[which].view(-1).get(e as i64).fill_(v0 - eps);
                let down = loss(&vars[0], &vars[1], &vars[2]).double_value(&[]);
                (up - down) / (2.0 * eps)
            });
            let an = g.reshape(-1).double_value(&[e as i64]);
            assert!(
                (fd - an).abs() < FD_TOL * (1.0 + an.abs()),
                "param {which} elem {e}: fd {fd} vs autograd {an}"
            );
        }
    }
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
