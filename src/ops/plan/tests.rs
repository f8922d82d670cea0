//! The plan's fill against a per-sample reference of torchvision's bilinear rule.

use calibconv_geometry::plan::FillPath;

use super::fill::{floor, Layout};
use super::{corners_of_top_left, padded_size, Border, ConvGeometry};

/// torchvision's bilinear interpolation with zeros outside, as (flat index or `None` for an
/// out-of-range corner, weight) for the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1). With
/// [`Border::WrapX`] corner columns are taken modulo `w` (never out of range).
fn bilinear_border(y: f64, x: f64, h: i64, w: i64, border: Border) -> [(Option<i64>, f64); 4] {
    let wrap = border == Border::WrapX;
    let x_outside = !wrap && (x <= -1.0 || x >= w as f64);
    if y <= -1.0 || y >= h as f64 || x_outside || !y.is_finite() || !x.is_finite() {
        return [(None, 0.0); 4];
    }
    let (y0, x0) = (floor(y) as i64, floor(x) as i64);
    let (ly, lx) = (y - y0 as f64, x - x0 as f64);
    let (hy, hx) = (1.0 - ly, 1.0 - lx);
    let at = |yy: i64, xx: i64| {
        let xx = if wrap { xx.rem_euclid(w) } else { xx };
        (yy >= 0 && yy < h && xx >= 0 && xx < w).then_some(yy * w + xx)
    };
    [
        (at(y0, x0), hy * hx),
        (at(y0, x0 + 1), hy * lx),
        (at(y0 + 1, x0), ly * hx),
        (at(y0 + 1, x0 + 1), ly * lx),
    ]
}

/// The corners and fractions of one sample as the plan stores them, from [`bilinear_border`].
fn reference_sample(
    y: f64,
    x: f64,
    h: i64,
    w: i64,
    border: Border,
    base: i64,
) -> ([i32; 4], [f64; 2]) {
    let corners = bilinear_border(y, x, h, w, border);
    let idx = corners.map(|(flat, _)| (base + flat.unwrap_or(h * w)) as i32);
    if corners.iter().any(|(flat, _)| flat.is_some()) {
        (idx, [y - floor(y), x - floor(x)])
    } else {
        (idx, [0.0, 0.0])
    }
}

#[test]
fn fill_row_matches_bilinear_sample_by_sample() {
    // Offsets around and past the border, non-finite ones, strides, dilations, padding,
    // per-item offsets and both border rules.
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let specials = [
        f64::NAN,
        f64::INFINITY,
        -f64::INFINITY,
        -1.0,
        0.0,
        1e12,
        -1e12,
    ];
    for (case, &(h, w, kernel, stride, padding, dilation, items, border)) in [
        (7, 9, [3, 3], [1, 1], [1, 1], [1, 1], None, Border::Zeros),
        (
            6,
            11,
            [3, 5],
            [2, 1],
            [0, 2],
            [1, 2],
            Some(2),
            Border::Zeros,
        ),
        (5, 8, [3, 3], [1, 2], [1, 1], [2, 1], None, Border::WrapX),
        (4, 6, [1, 3], [1, 1], [0, 1], [1, 1], Some(3), Border::WrapX),
    ]
    .iter()
    .enumerate()
    {
        let geom = ConvGeometry::new(kernel, stride, padding, dilation);
        let [ho, wo] = geom.output_size([h, w]).unwrap();
        let taps = (kernel[0] * kernel[1]) as usize;
        let n_items = items.unwrap_or(1);
        let plane = (ho * wo) as usize;
        let off: Vec<f64> = (0..n_items as usize * 2 * taps * plane)
            .map(|i| {
                if i % 23 == 5 {
                    specials[i / 23 % specials.len()]
                } else {
                    // Mostly within a few pixels, sometimes far outside.
                    let spread = if i % 7 == 0 {
                        3.0 * (h + w) as f64
                    } else {
                        3.0
                    };
                    (next() - 0.5) * 2.0 * spread
                }
            })
            .collect();
        let layout = Layout {
            h,
            w,
            ho,
            wo,
            geom,
            per_item: items.is_some(),
            border,
        };
        let row = wo as usize * taps;
        // The geometry crate's fill of one row, through both clones of the fill without wrap
        // (AVX2 where the CPU has it, and portable).
        let plan_layout = layout.plan_layout();
        let paths = [FillPath::Fastest, FillPath::Portable];
        for (r, path) in (0..(n_items * ho) as usize).flat_map(|r| paths.map(|p| (r, p))) {
            let mut idx = vec![-7i32; 4 * row];
            let mut frac = vec![-7.0f64; 2 * row];
            let mut top_left = vec![-7i32; row];
            let reach = plan_layout.fill_row(&off, r, &mut top_left, &mut frac, path);
            // The ATen path's corner indices, derived from the top-left corners.
            corners_of_top_left(&top_left, [h, w], border, &mut idx);
            let (item, oy) = (r as i64 / ho, r as i64 % ho);
            let base = if items.is_some() {
                item * (h * w + 1)
            } else {
                0
            };
            let [hp, wp] = padded_size([h, w]);
            let padded_base = if items.is_some() { item * hp * wp } else { 0 };
            let mut want_reach = [i32::MAX, i32::MIN];
            for ox in 0..wo {
                for k in 0..taps as i64 {
                    let (i, j) = (k / kernel[1], k % kernel[1]);
                    let p = (oy * wo + ox) as usize;
                    let at = |c: i64| off[((item * 2 * taps as i64 + c) as usize) * plane + p];
                    let y = (oy * stride[0] - padding[0] + i * dilation[0]) as f64 + at(2 * k);
                    let x = (ox * stride[1] - padding[1] + j * dilation[1]) as f64 + at(2 * k + 1);
                    let (want_idx, want_frac) = reference_sample(y, x, h, w, border, base);
                    let s = (ox * taps as i64 + k) as usize;
                    let what = format!("case {case}, row {r}, ox {ox}, tap {k}: y {y}, x {x}");
                    assert_eq!(idx[4 * s..4 * s + 4], want_idx, "{what}");
                    assert_eq!(frac[2 * s..2 * s + 2], want_frac, "{what}");
                    let inside = want_frac != [0.0, 0.0]
                        || want_idx.iter().any(|&c| c != (base + h * w) as i32);
                    // The padded input: the top-left corner (its column modulo w with
                    // wrap), or the zero block at row h, column -1.
                    let want_top_left = if inside {
                        let x0 = floor(x) as i64;
                        let x0 = if border == Border::WrapX {
                            x0.rem_euclid(w)
                        } else {
                            x0
                        };
                        padded_base + (floor(y) as i64 + 1) * wp + x0 + 1
                    } else {
                        padded_base + (h + 1) * wp
                    };
                    assert_eq!(top_left[s] as i64, want_top_left, "{what}");
                    if inside {
                        let y0 = floor(y) as i32;
                        want_reach = [want_reach[0].min(y0), want_reach[1].max(y0 + 1)];
                    }
                }
            }
            assert_eq!(reach, want_reach, "case {case}, row {r}");
        }
    }
}

fn bilinear(y: f64, x: f64, h: i64, w: i64) -> [(Option<i64>, f64); 4] {
    bilinear_border(y, x, h, w, Border::Zeros)
}

#[test]
fn wrap_x_takes_columns_modulo_the_width() {
    // x = -0.25 on a 5-wide row 1: corners at columns -1 -> 4 and 0, weights 0.25 / 0.75.
    let c = bilinear_border(1.0, -0.25, 4, 5, Border::WrapX);
    assert_eq!((c[0].0, c[1].0), (Some(5 + 4), Some(5)));
    assert!((c[0].1 - 0.25).abs() < 1e-12 && (c[1].1 - 0.75).abs() < 1e-12);
    // Far outside: one period further gives the same corners; rows still read zero.
    let far = bilinear_border(1.0, -0.25 + 10.0, 4, 5, Border::WrapX);
    assert_eq!((far[0].0, far[1].0), (Some(9), Some(5)));
    assert!(bilinear_border(-1.0, 2.0, 4, 5, Border::WrapX)
        .iter()
        .all(|(i, w)| i.is_none() && *w == 0.0));
    // The same sample with zeros outside loses the wrapped corner.
    assert_eq!(bilinear(1.0, -0.25, 4, 5)[0].0, None);
}

#[test]
fn bilinear_weights_sum_to_one_inside() {
    let c = bilinear(1.25, 2.5, 4, 5);
    let total: f64 = c.iter().map(|(_, w)| w).sum();
    assert!((total - 1.0).abs() < 1e-12);
    assert_eq!(c[0].0, Some(5 + 2));
    assert!((c[0].1 - 0.75 * 0.5).abs() < 1e-12);
}

#[test]
fn bilinear_is_zero_outside_and_partial_at_border() {
    assert!(bilinear(-1.0, 0.0, 4, 4)
        .iter()
        .all(|(i, w)| i.is_none() && *w == 0.0));
    assert!(bilinear(0.0, 4.0, 4, 4).iter().all(|(i, _)| i.is_none()));
    // y in (-1, 0): the top corners fall outside, the bottom ones keep weight ly.
    let c = bilinear(-0.5, 1.0, 4, 4);
    assert_eq!(c[0].0, None);
    assert_eq!(c[2].0, Some(1));
    assert!((c[2].1 - 0.5).abs() < 1e-12);
}
