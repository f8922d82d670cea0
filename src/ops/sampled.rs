//! The deformable convolution differentiable in its offsets: for offsets that are learned
//! (DCN, Dai et al. 2017), where the sampling plan cannot be built once.
//!
//! Same semantics as [`super::deform_conv2d`] (torchvision's bilinear sampling with zeros
//! outside: a location with `y <= -1`, `y >= H`, `x <= -1` or `x >= W` samples 0, and each corner
//! off the input contributes 0), composed of ATen ops that libtorch differentiates, offsets
//! included: every tap's sample positions go through one `grid_sampler_2d` (bilinear, zeros
//! padding, `align_corners = true`, whose pixel `p` is the normalised coordinate
//! `2 p / (n - 1) - 1`: exactly torchvision's bilinear rule), the taps stacked along the rows of
//! the grid, and one batched matrix product applies the weight. It builds the column matrix
//! `[B, C*kh*kw, H_out*W_out]` on every call, so it costs more than the planned op; it is meant
//! for the layers whose offsets learn.
//!
//! Gradients with respect to the offsets agree with torchvision's wherever the bilinear weights
//! are differentiable (not on integer sample coordinates, where both pick one side).

use tch::{Kind, Tensor};

use super::{groups_fit, size4, ConvGeometry, INPUT_DIMS, WEIGHT_DIMS};
use crate::error::{Error, Result};

/// Deformable 2-D convolution, differentiable in `input`, `offsets`, `weight` and `bias`.
///
/// # Shapes
/// - `input`: `[B, C_in, H, W]` with `H, W >= 2`, float32 or float64
/// - `offsets`: `[B, 2*kh*kw, H_out, W_out]` or `[2*kh*kw, H_out, W_out]` (shared by the batch),
///   per tap (row-major) the pair `(dy, dx)`
/// - `weight`: `[C_out, C_in / groups, kh, kw]`; `bias`: `[C_out]`
/// - output: `[B, C_out, H_out, W_out]`
pub fn f_deform_conv2d_sampled(
    input: &Tensor,
    offsets: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    geometry: ConvGeometry,
    groups: i64,
) -> Result<Tensor> {
    let (b, c_in, h, w) = size4(input, "input", INPUT_DIMS)?;
    let (c_out, c_pg, kh, kw) = size4(weight, "weight", WEIGHT_DIMS)?;
    if !groups_fit(groups, c_in, c_out, c_pg) {
        return Err(Error::InvalidArgument(format!(
            "groups = {groups} does not fit C_in = {c_in}, C_out = {c_out} and weight {:?}",
            weight.size()
        )));
    }
    if h < 2 || w < 2 {
        return Err(Error::InvalidArgument(format!(
            "the sampled deformable convolution needs an input of at least 2x2, got {h}x{w}"
        )));
    }
    let [ho, wo] = geometry.output_size([h, w])?;
    let taps = kh * kw;
    let offsets = match offsets.dim() {
        3 => offsets.unsqueeze(0).expand([b, -1, -1, -1], false),
        _ => offsets.shallow_clone(),
    };
    if offsets.size() != [b, 2 * taps, ho, wo] {
        return Err(Error::InvalidArgument(format!(
            "offsets must be [B, 2*kh*kw, H_out, W_out] = [{b}, {}, {ho}, {wo}] (or without B), \
             got {:?}",
            2 * taps,
            offsets.size()
        )));
    }
    let (kind, device) = (input.kind(), input.device());
    // The regular grid of every tap: [taps, H_out, W_out] rows and columns.
    let [sy, sx] = geometry.stride;
    let [py, px] = geometry.padding;
    let [dy, dx] = geometry.dilation;
    let opts = (Kind::Float, device);
    let oy = Tensor::arange(ho, opts).view([1, ho, 1]) * sy as f64 - py as f64;
    let ox = Tensor::arange(wo, opts).view([1, 1, wo]) * sx as f64 - px as f64;
    let tap = Tensor::arange(taps, (Kind::Int64, device));
    let ty = (tap.floor_divide_scalar(kw).to_kind(Kind::Float) * dy as f64).view([taps, 1, 1]);
    let tx = (tap.remainder(kw).to_kind(Kind::Float) * dx as f64).view([taps, 1, 1]);
    let base_y = (oy + ty).to_kind(kind);
    let base_x = (ox + tx).to_kind(kind);
    let off = offsets.view([b, taps, 2, ho, wo]);
    let y = off.select(2, 0) + base_y; // [B, taps, H_out, W_out]
    let x = off.select(2, 1) + base_x;
    // Normalised for align_corners = true: pixel p is 2 p / (n - 1) - 1.
    let gy = y * (2.0 / (h - 1) as f64) - 1.0;
    let gx = x * (2.0 / (w - 1) as f64) - 1.0;
    let grid = Tensor::stack(&[gx, gy], -1).view([b, taps * ho, wo, 2]);
    // [B, C_in, taps * H_out, W_out] -> columns [B, groups, C_pg * taps, P]
    let sampled = input.f_grid_sampler_2d(&grid, 0, 0, true)?;
    let p = ho * wo;
    let cols = sampled.view([b, groups, c_pg * taps, p]);
    let wmat = weight.reshape([groups, c_out / groups, c_pg * taps]);
    let out = wmat.unsqueeze(0).matmul(&cols).view([b, c_out, ho, wo]);
    Ok(match bias {
        Some(bias) => out + bias.view([1, c_out, 1, 1]),
        None => out,
    })
}

#[cfg(test)]
mod tests {
    use tch::{Device, Kind, Tensor};

    use super::*;
    use crate::ops::{deform_conv2d_planned_with, Backend, Border, SamplingPlan};

    /// The sampled op agrees with the planned one (value, input and weight gradients) on random
    /// offsets that reach off the input, with stride, dilation and groups.
    #[test]
    fn agrees_with_the_planned_op_in_float64() {
        tch::manual_seed(7);
        let opts = (Kind::Double, Device::Cpu);
        for (stride, pad, dil, groups) in [(1, 1, 1, 1), (2, 1, 1, 2), (1, 2, 2, 1)] {
            let g = ConvGeometry::new([3, 3], [stride; 2], [pad; 2], [dil; 2]);
            let [ho, wo] = g.output_size([9, 11]).unwrap();
            let x = Tensor::randn([2, 4, 9, 11], opts);
            let wt = Tensor::randn([6, 4 / groups, 3, 3], opts) * 0.3;
            let bias = Tensor::randn([6], opts);
            let off = Tensor::randn([2, 18, ho, wo], opts) * 2.0;
            let plan =
                SamplingPlan::with_border(&off, [9, 11], g, Kind::Double, Border::Zeros).unwrap();
            let leaf = |t: &Tensor| t.detach().set_requires_grad(true);
            let (x1, w1, x2, w2) = (leaf(&x), leaf(&wt), leaf(&x), leaf(&wt));
            let a = f_deform_conv2d_sampled(&x1, &off, &w1, Some(&bias), g, groups).unwrap();
            let r = deform_conv2d_planned_with(&x2, &plan, &w2, Some(&bias), groups, Backend::Aten)
                .unwrap();
            let probe = Tensor::randn(a.size(), opts);
            (&a * &probe).sum(Kind::Double).backward();
            (&r * &probe).sum(Kind::Double).backward();
            let diff = |p: &Tensor, q: &Tensor| (p - q).abs().max().double_value(&[]);
            assert!(diff(&a, &r) < 1e-12, "value {}", diff(&a, &r));
            assert!(diff(&x1.grad(), &x2.grad()) < 1e-12);
            assert!(diff(&w1.grad(), &w2.grad()) < 1e-12);
        }
    }

    #[test]
    fn offset_gradients_match_central_differences() {
        tch::manual_seed(3);
        let opts = (Kind::Double, Device::Cpu);
        let g = ConvGeometry::new([3, 3], [1, 1], [1, 1], [1, 1]);
        let x = Tensor::randn([1, 2, 6, 7], opts);
        let wt = Tensor::randn([3, 2, 3, 3], opts);
        let off = (Tensor::randn([1, 18, 6, 7], opts) * 1.5).set_requires_grad(true);
        let probe = Tensor::randn([1, 3, 6, 7], opts);
        let loss = |o: &Tensor| {
            (f_deform_conv2d_sampled(&x, o, &wt, None, g, 1).unwrap() * &probe).sum(Kind::Double)
        };
        loss(&off).backward();
        let grad = off.grad().view([-1]);
        let flat = off.detach().view([-1]);
        for i in [0i64, 17, 100, 333, 700] {
            let e = Tensor::zeros_like(&flat);
            let _ = e.get(i).fill_(1e-6);
            let plus = loss(&(&flat + &e).view([1, 18, 6, 7])).double_value(&[]);
            let minus = loss(&(&flat - &e).view([1, 18, 6, 7])).double_value(&[]);
            let fd = (plus - minus) / 2e-6;
            let an = grad.double_value(&[i]);
            assert!(
                (fd - an).abs() < 1e-6 * (1.0 + an.abs()),
                "{i}: fd {fd} vs {an}"
            );
        }
    }

    #[test]
    fn bad_shapes_are_errors() {
        let opts = (Kind::Float, Device::Cpu);
        let g = ConvGeometry::new([3, 3], [1, 1], [1, 1], [1, 1]);
        let x = Tensor::zeros([1, 2, 5, 5], opts);
        let w = Tensor::zeros([3, 2, 3, 3], opts);
        let e = f_deform_conv2d_sampled(&x, &Tensor::zeros([18, 4, 5], opts), &w, None, g, 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("offsets must be"), "{e}");
        let e = f_deform_conv2d_sampled(&x, &Tensor::zeros([18, 5, 5], opts), &w, None, g, 3)
            .unwrap_err()
            .to_string();
        assert!(e.contains("groups"), "{e}");
    }
}
