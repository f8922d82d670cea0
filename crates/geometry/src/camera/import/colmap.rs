//! COLMAP `cameras.txt`.

use std::path::Path;

use super::tree::{expect_len, parse_float};
use super::{camera_error, format_error, ImportOptions, Model, Parsed};
use crate::error::Result;

/// COLMAP's image coordinates put the centre of the top-left pixel at (0.5, 0.5).
const COLMAP_PIXEL_CENTRE: f64 = 0.5;

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let lines: Vec<(usize, Vec<&str>)> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.split_whitespace().collect()))
        .collect();
    let id_of = |tokens: &[&str]| tokens.first().and_then(|t| t.parse::<usize>().ok());
    let (line, tokens) = match options.camera {
        None => lines.first(),
        Some(id) => lines.iter().find(|(_, t)| id_of(t) == Some(id)),
    }
    .ok_or_else(|| {
        let ids: Vec<usize> = lines.iter().filter_map(|(_, t)| id_of(t)).collect();
        format_error(
            path,
            match options.camera {
                Some(id) => format!("no camera with CAMERA_ID {id} (found {ids:?})"),
                None => "no camera line (CAMERA_ID MODEL WIDTH HEIGHT PARAMS...)".to_string(),
            },
        )
    })?;
    let field = |what: &str| format!("line {line}: {what}");
    if tokens.len() < 4 {
        return Err(camera_error(
            path,
            &field("CAMERA_ID MODEL WIDTH HEIGHT"),
            format!("expected at least 4 tokens, found {}", tokens.len()),
        ));
    }
    let id = tokens[0];
    let name = tokens[1];
    let dim = |t: &str, what: &str| {
        t.parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| camera_error(path, &field(what), format!("`{t}` is not a size")))
    };
    let size = [dim(tokens[2], "WIDTH")?, dim(tokens[3], "HEIGHT")?];
    let params = tokens[4..]
        .iter()
        .map(|t| {
            parse_float(t).ok_or_else(|| {
                camera_error(path, &field("PARAMS"), format!("`{t}` is not a number"))
            })
        })
        .collect::<Result<Vec<f64>>>()?;
    let model = model(name, &params, *line, path)?;
    Ok(Parsed {
        model,
        size,
        source: format!("colmap camera {id} ({name})"),
        notes: vec![
            "cx, cy: COLMAP's minus 0.5 px (COLMAP puts the top-left pixel centre at (0.5, 0.5), \
             this file at (0, 0))"
                .to_string(),
        ],
    })
}

/// The model of a camera line: `name` (COLMAP's `MODEL`) with its `PARAMS`, on line `line`; the
/// principal point moved by [`COLMAP_PIXEL_CENTRE`].
///
/// `PARAMS` start with the intrinsics, `f, cx, cy` (one focal length: the `SIMPLE_*` models and
/// `RADIAL`) or `fx, fy, cx, cy`, and go on with the distortion's coefficients.
fn model(name: &str, params: &[f64], line: usize, path: &Path) -> Result<Model> {
    let field = |what: &str| format!("line {line}: {what}");
    let c = COLMAP_PIXEL_CENTRE;
    // `PARAMS` checked to be `names` (`n` of them), split into `[fx, fy, cx, cy]` and the rest.
    let split = |n: usize, names: &str, simple: bool| -> Result<([f64; 4], &[f64])> {
        let what = format!("{name} {names}");
        expect_len(params, n, path, &field("PARAMS"), &what)?;
        Ok(if simple {
            let [f, cx, cy] = [params[0], params[1], params[2]];
            ([f, f, cx - c, cy - c], &params[3..])
        } else {
            let [fx, fy, cx, cy] = [params[0], params[1], params[2], params[3]];
            ([fx, fy, cx - c, cy - c], &params[4..])
        })
    };
    let simple = |n: usize, names: &str| split(n, names, true);
    let full = |n: usize, names: &str| split(n, names, false);
    Ok(match name {
        "SIMPLE_PINHOLE" => Model::Pinhole {
            f: simple(3, "f, cx, cy")?.0,
        },
        "PINHOLE" => Model::Pinhole {
            f: full(4, "fx, fy, cx, cy")?.0,
        },
        "SIMPLE_RADIAL" => {
            let (f, k) = simple(4, "f, cx, cy, k")?;
            Model::radtan(f, [k[0], 0.0, 0.0], [0.0, 0.0])
        }
        "RADIAL" => {
            let (f, k) = simple(5, "f, cx, cy, k1, k2")?;
            Model::radtan(f, [k[0], k[1], 0.0], [0.0, 0.0])
        }
        "OPENCV" => {
            let (f, d) = full(8, "fx, fy, cx, cy, k1, k2, p1, p2")?;
            Model::radtan(f, [d[0], d[1], 0.0], [d[2], d[3]])
        }
        "FULL_OPENCV" => {
            let (f, d) = full(12, "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6")?;
            Model::RadTan {
                f,
                k: [d[0], d[1], d[4], d[5], d[6], d[7]],
                p: [d[2], d[3]],
                rpmax: 0.0,
            }
        }
        "FOV" => {
            let (f, d) = full(5, "fx, fy, cx, cy, omega")?;
            Model::Fov { f, w: d[0] }
        }
        "OPENCV_FISHEYE" => {
            let (f, k) = full(8, "fx, fy, cx, cy, k1, k2, k3, k4")?;
            Model::KannalaBrandt {
                f,
                k: [k[0], k[1], k[2], k[3]],
            }
        }
        other => {
            return Err(camera_error(
                path,
                &field("MODEL"),
                format!(
                    "COLMAP model `{other}` is not supported (supported: OPENCV_FISHEYE, \
                     OPENCV, FULL_OPENCV, FOV, PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL)"
                ),
            ))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every model's `PARAMS` land in their fields: all values distinct, so a swapped index shows.
    #[test]
    fn params_land_in_their_fields() {
        let c = COLMAP_PIXEL_CENTRE;
        let params: Vec<f64> = (1..=13).map(f64::from).collect();
        let (simple_f, full_f) = ([1.0, 1.0, 2.0 - c, 3.0 - c], [1.0, 2.0, 3.0 - c, 4.0 - c]);
        let cases = [
            ("SIMPLE_PINHOLE", 3, Model::Pinhole { f: simple_f }),
            ("PINHOLE", 4, Model::Pinhole { f: full_f }),
            (
                "SIMPLE_RADIAL",
                4,
                Model::radtan(simple_f, [4.0, 0.0, 0.0], [0.0, 0.0]),
            ),
            (
                "RADIAL",
                5,
                Model::radtan(simple_f, [4.0, 5.0, 0.0], [0.0, 0.0]),
            ),
            (
                "OPENCV",
                8,
                Model::radtan(full_f, [5.0, 6.0, 0.0], [7.0, 8.0]),
            ),
            (
                "FULL_OPENCV",
                12,
                Model::RadTan {
                    f: full_f,
                    k: [5.0, 6.0, 9.0, 10.0, 11.0, 12.0],
                    p: [7.0, 8.0],
                    rpmax: 0.0,
                },
            ),
            ("FOV", 5, Model::Fov { f: full_f, w: 5.0 }),
            (
                "OPENCV_FISHEYE",
                8,
                Model::KannalaBrandt {
                    f: full_f,
                    k: [5.0, 6.0, 7.0, 8.0],
                },
            ),
        ];
        let path = Path::new("cameras.txt");
        for (name, n, expected) in cases {
            let got = model(name, &params[..n], 1, path).unwrap();
            assert_eq!(format!("{got:?}"), format!("{expected:?}"), "{name}");
            assert!(model(name, &params[..n + 1], 1, path).is_err(), "{name}");
        }
    }
}
