//! OCamCalib `calib_results.txt` (Scaramuzza's model).

use std::path::Path;

use super::tree::{expect_len, parse_float};
use super::{camera_error, format_error, Model, Parsed};
use crate::error::Result;

pub(super) fn read(text: &str, path: &Path) -> Result<Parsed> {
    // The data lines, in order, between '#' comment lines (ocam_functions.c, get_ocam_model).
    let lines: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l))
        .collect();
    const BLOCKS: [&str; 5] = [
        "direct polynomial (length, a0 .. aN)",
        "inverse polynomial (length, b0 .. bM)",
        "centre (row, column)",
        "affine parameters (c, d, e)",
        "image size (height, width)",
    ];
    if lines.len() < BLOCKS.len() {
        return Err(format_error(
            path,
            format!(
                "expected {} data lines ({}), found {}",
                BLOCKS.len(),
                BLOCKS.join("; "),
                lines.len()
            ),
        ));
    }
    let values = |k: usize| -> Result<Vec<f64>> {
        let (line, text) = lines[k];
        text.split_whitespace()
            .map(|t| {
                parse_float(t).ok_or_else(|| {
                    camera_error(
                        path,
                        &format!("line {line}: {}", BLOCKS[k]),
                        format!("`{t}` is not a number"),
                    )
                })
            })
            .collect()
    };
    let block_field = |k: usize| format!("line {}: {}", lines[k].0, BLOCKS[k]);
    let polynomial = |k: usize| -> Result<Vec<f64>> {
        let v = values(k)?;
        let n = v.first().copied().unwrap_or(-1.0);
        if !(n >= 1.0 && n.fract() == 0.0 && v.len() == n as usize + 1) {
            return Err(camera_error(
                path,
                &block_field(k),
                format!(
                    "the first number is the count of coefficients that follow: {n} vs {}",
                    v.len().saturating_sub(1)
                ),
            ));
        }
        Ok(v[1..].to_vec())
    };
    let poly = polynomial(0)?;
    let inv_poly = polynomial(1)?;
    let fixed = |k: usize, n: usize| -> Result<Vec<f64>> {
        let v = values(k)?;
        expect_len(&v, n, path, &block_field(k), BLOCKS[k])?;
        Ok(v)
    };
    let centre = fixed(2, 2)?;
    let cde = fixed(3, 3)?;
    let hw = fixed(4, 2)?;
    let dim = |x: f64, what: &str| {
        if x >= 1.0 && x.fract() == 0.0 {
            Ok(x as usize)
        } else {
            Err(camera_error(
                path,
                &block_field(4),
                format!("{what} = {x} is not a size"),
            ))
        }
    };
    let size = [dim(hw[1], "width")?, dim(hw[0], "height")?];
    Ok(Parsed {
        model: Model::Scaramuzza {
            poly,
            inv_poly,
            // OCamCalib: xc = row, yc = column.
            centre: [centre[1], centre[0]],
            cde: [cde[0], cde[1], cde[2]],
        },
        size,
        source: "ocamcalib calib_results".to_string(),
        notes: vec![
            "cx = OCamCalib's yc (column), cy = its xc (row); c, d, e in OCamCalib's order"
                .to_string(),
        ],
    })
}
