//! `calibconv::ops::deform_conv2d` against `torchvision.ops.deform_conv2d`.
//!
//! Fixture: `tests/golden/deform_conv2d.safetensors`, written by `tools/make_fixtures.py` (see
//! `tests/golden/README.md`). Per case `c{n}`: `input`, `offset` (`[2K, Ho, Wo]` shared by the
//! batch, or `[B, 2K, Ho, Wo]` per item), `weight`, optional `bias`, `probe`, and torchvision's
//! `output` and the gradients of `(output * probe).sum()` with respect to input, weight, bias
//! and the offsets (`grad_offset`, per item `[B, 2K, Ho, Wo]`: what learned offsets train on,
//! checked against `calibconv::ops::f_deform_conv2d_sampled`); `meta` = `[stride_h, stride_w, pad_h, pad_w, dil_h, dil_w, groups, has_bias]`. The
//! inputs are float32; the references were computed in float64 and stored as float32.

use std::collections::BTreeMap;
use std::panic::AssertUnwindSafe;

use calibconv::ops::{deform_conv2d, f_deform_conv2d_sampled, ConvGeometry};
use tch::{Kind, Tensor};

use crate::common::{golden, max_rel, read_safetensors};

/// Float32 run vs float64 reference: sums of at most 8 x 25 products of O(1) values carry
/// round-off ~1e-6 of the largest value; 1e-4 is margin, while a wrong tap, border rule or
/// bilinear weight is an error of order 1e-2 or more.
const REL_TOL: f64 = 1e-4;
/// Float64 run vs the float64 reference rounded to float32 on storage: the rounding is at most
/// 2^-24 ~ 6e-8 of each value; 1e-6 is margin above that and far below a real error.
const F64_REL_TOL: f64 = 1e-6;
/// The fixture holds this many cases or more; fewer means a truncated or wrong file.
const MIN_CASES: usize = 7;

/// One fixture case.
struct Case {
    name: String,
    input: Tensor,
    offset: Tensor,
    weight: Tensor,
    bias: Option<Tensor>,
    probe: Tensor,
    output: Tensor,
    grad_input: Tensor,
    grad_weight: Tensor,
    grad_bias: Option<Tensor>,
    grad_offset: Tensor,
    stride: [i64; 2],
    padding: [i64; 2],
    dilation: [i64; 2],
    groups: i64,
}

/// What the library computes for a case.
struct Run {
    output: Tensor,
    grad_input: Tensor,
    grad_weight: Tensor,
    grad_bias: Option<Tensor>,
}

fn cases() -> Vec<Case> {
    let mut all = read_safetensors(&golden("deform_conv2d.safetensors"));
    let mut names: Vec<String> = all
        .keys()
        .filter_map(|k| k.strip_suffix(".meta").map(str::to_string))
        .collect();
    names.sort_by_key(|n| n[1..].parse::<usize>().unwrap_or(usize::MAX));
    let cases: Vec<Case> = names.into_iter().map(|n| take_case(&mut all, n)).collect();
    assert!(
        all.is_empty(),
        "unexpected tensors in the fixture: {:?}",
        all.keys()
    );
    cases
}

fn take_case(all: &mut BTreeMap<String, Tensor>, name: String) -> Case {
    let mut take = |field: &str| all.remove(&format!("{name}.{field}"));
    let mut need = |field: &str| {
        take(field).unwrap_or_else(|| panic!("{name}: no `{name}.{field}` in the fixture"))
    };
    let meta = need("meta");
    assert_eq!(meta.kind(), Kind::Int64, "{name}.meta");
    let meta = Vec::<i64>::try_from(&meta).unwrap();
    assert_eq!(meta.len(), 8, "{name}.meta: {meta:?}");
    let (input, offset, weight, probe) =
        (need("input"), need("offset"), need("weight"), need("probe"));
    let (output, grad_input, grad_weight) =
        (need("output"), need("grad_input"), need("grad_weight"));
    let grad_offset = need("grad_offset");
    let (bias, grad_bias) = (take("bias"), take("grad_bias"));
    let has_bias = meta[7] != 0;
    assert_eq!(
        bias.is_some(),
        has_bias,
        "{name}: bias present vs meta {meta:?}"
    );
    assert_eq!(
        grad_bias.is_some(),
        has_bias,
        "{name}: grad_bias present vs meta {meta:?}"
    );
    Case {
        name,
        input,
        offset,
        weight,
        bias,
        probe,
        output,
        grad_input,
        grad_weight,
        grad_bias,
        grad_offset,
        stride: [meta[0], meta[1]],
        padding: [meta[2], meta[3]],
        dilation: [meta[4], meta[5]],
        groups: meta[6],
    }
}

/// Runs the library on a case in `kind`, with gradients of `(output * probe).sum()`.
fn run(case: &Case, kind: Kind) -> Run {
    let leaf = |t: &Tensor| t.to_kind(kind).detach().set_requires_grad(true);
    let input = leaf(&case.input);
    let weight = leaf(&case.weight);
    let bias = case.bias.as_ref().map(leaf);
    let output = deform_conv2d(
        &input,
        &case.offset.to_kind(kind),
        &weight,
        bias.as_ref(),
        case.stride,
        case.padding,
        case.dilation,
        case.groups,
    );
    assert_eq!(
        output.size(),
        case.output.size(),
        "{}: output shape",
        case.name
    );
    (&output * case.probe.to_kind(kind)).sum(kind).backward();
    Run {
        output: output.detach(),
        grad_input: input.grad(),
        grad_weight: weight.grad(),
        grad_bias: bias.map(|b| b.grad()),
    }
}

/// Compares one property over every case; the message names each failing case.
fn check(what: &str, tol: f64, kind: Kind, pick: impl Fn(&Case, &Run) -> Option<(Tensor, Tensor)>) {
    let cases = cases();
    assert!(
        cases.len() >= MIN_CASES,
        "only {} cases in the fixture",
        cases.len()
    );
    let mut failures = Vec::new();
    let mut compared = 0;
    for case in &cases {
        // A panic inside the library is reported with the case's name like a mismatch.
        let ran = match std::panic::catch_unwind(AssertUnwindSafe(|| run(case, kind))) {
            Ok(ran) => ran,
            Err(payload) => {
                let msg = payload
                    .downcast_ref::<String>()
                    .map(String::as_str)
                    .or_else(|| payload.downcast_ref::<&str>().copied())
                    .unwrap_or("(non-string panic)");
                let head: String = msg.chars().take(240).collect();
                failures.push(format!("{} `{}`: panicked: {head}", case.name, what));
                continue;
            }
        };
        if let Some((ours, reference)) = pick(case, &ran) {
            let rel = max_rel(&ours, &reference);
            println!("{} {what}: max_rel {rel:.3e}", case.name);
            if rel.is_nan() || rel >= tol {
                failures.push(format!("{} `{}`: max_rel {rel:.3e}", case.name, what));
            }
            compared += 1;
        }
    }
    assert!(
        compared > 0 || !failures.is_empty(),
        "{what}: nothing compared"
    );
    assert!(
        failures.is_empty(),
        "{what} differs from torchvision beyond {tol:e}:\n{}",
        failures.join("\n")
    );
}

#[test]
fn fixture_has_enough_cases_covering_the_geometries() {
    let cases = cases();
    assert!(
        cases.len() >= MIN_CASES,
        "only {} cases in the fixture",
        cases.len()
    );
    let any = |f: &dyn Fn(&Case) -> bool| cases.iter().any(f);
    assert!(any(&|c| c.stride != [1, 1]), "no strided case");
    assert!(any(&|c| c.dilation != [1, 1]), "no dilated case");
    assert!(any(&|c| c.groups > 1), "no grouped case");
    assert!(any(&|c| c.bias.is_none()), "no case without bias");
    assert!(any(&|c| c.offset.dim() == 4), "no per-item offsets case");
    assert!(
        any(&|c| c.weight.size()[2] != c.weight.size()[3]),
        "no non-square kernel"
    );
    assert!(
        any(&|c| c.input.size()[2] != c.input.size()[3]),
        "no non-square input"
    );
}

/// What [`check`] compares: the output or one of the gradients.
#[derive(Clone, Copy, Debug)]
enum Quantity {
    Output,
    GradInput,
    GradWeight,
    /// Only in cases with a bias.
    GradBias,
}

impl Quantity {
    const ALL: [Quantity; 4] = [
        Quantity::Output,
        Quantity::GradInput,
        Quantity::GradWeight,
        Quantity::GradBias,
    ];

    fn name(self) -> &'static str {
        match self {
            Quantity::Output => "output",
            Quantity::GradInput => "grad_input",
            Quantity::GradWeight => "grad_weight",
            Quantity::GradBias => "grad_bias",
        }
    }

    /// The library's and torchvision's values, or `None` where the case has none.
    fn pick(self, c: &Case, r: &Run) -> Option<(Tensor, Tensor)> {
        let (ours, reference) = match self {
            Quantity::Output => (&r.output, &c.output),
            Quantity::GradInput => (&r.grad_input, &c.grad_input),
            Quantity::GradWeight => (&r.grad_weight, &c.grad_weight),
            Quantity::GradBias => (r.grad_bias.as_ref()?, c.grad_bias.as_ref()?),
        };
        Some((ours.shallow_clone(), reference.shallow_clone()))
    }
}

/// One test per quantity, in float32 against [`REL_TOL`].
macro_rules! float32_tests {
    ($($test:ident: $quantity:ident,)*) => {$(
        #[test]
        fn $test() {
            let q = Quantity::$quantity;
            check(q.name(), REL_TOL, Kind::Float, |c, r| q.pick(c, r));
        }
    )*};
}

float32_tests! {
    output_matches_torchvision: Output,
    grad_input_matches_torchvision: GradInput,
    grad_weight_matches_torchvision: GradWeight,
    grad_bias_matches_torchvision: GradBias,
}

/// The same comparisons in float64: the library is then held to the float32 rounding of the
/// stored reference instead of float32 arithmetic.
#[test]
fn float64_output_and_gradients_match_torchvision() {
    for q in Quantity::ALL {
        let what = format!("float64 {}", q.name());
        check(&what, F64_REL_TOL, Kind::Double, |c, r| q.pick(c, r));
    }
}

/// The offset-differentiable op (learned offsets) against torchvision in float64: the output
/// and every gradient, the offsets' included, on every case (per-item offsets as leaves).
#[test]
fn the_sampled_op_and_its_offset_gradient_match_torchvision() {
    let mut failures = Vec::new();
    for case in cases() {
        let kind = Kind::Double;
        let leaf = |t: &Tensor| t.to_kind(kind).detach().set_requires_grad(true);
        let b = case.input.size()[0];
        let per_item = match case.offset.dim() {
            3 => case.offset.unsqueeze(0).expand([b, -1, -1, -1], false),
            _ => case.offset.shallow_clone(),
        };
        let (input, weight, offset) = (leaf(&case.input), leaf(&case.weight), leaf(&per_item));
        let bias = case.bias.as_ref().map(leaf);
        let [kh, kw] = [case.weight.size()[2], case.weight.size()[3]];
        let geometry = ConvGeometry::new([kh, kw], case.stride, case.padding, case.dilation);
        let output = f_deform_conv2d_sampled(
            &input,
            &offset,
            &weight,
            bias.as_ref(),
            geometry,
            case.groups,
        )
        .unwrap();
        (&output * case.probe.to_kind(kind)).sum(kind).backward();
        let mut pairs = vec![
            ("output", output.detach(), &case.output),
            ("grad_input", input.grad(), &case.grad_input),
            ("grad_weight", weight.grad(), &case.grad_weight),
            ("grad_offset", offset.grad(), &case.grad_offset),
        ];
        if let (Some(b), Some(r)) = (&bias, &case.grad_bias) {
            pairs.push(("grad_bias", b.grad(), r));
        }
        for (what, ours, reference) in pairs {
            let rel = max_rel(&ours, reference);
            println!("{} sampled {what}: max_rel {rel:.3e}", case.name);
            if rel.is_nan() || rel >= F64_REL_TOL {
                failures.push(format!("{} {what}: max_rel {rel:.3e}", case.name));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
