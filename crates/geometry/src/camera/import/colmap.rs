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
fn model(name: &str, params: &[f64], line: usize, path: &Path) -> Result<Model> {
    let field = |what: &str| format!("line {line}: {what}");
    let count = |n: usize, names: &str| {
        expect_len(
            params,
            n,
            path,
            &field("PARAMS"),
            &format!("{name} {names}"),
        )
    };
    let c = COLMAP_PIXEL_CENTRE;
    Ok(match name {
        "SIMPLE_PINHOLE" => {
            count(3, "f, cx, cy")?;
            Model::Pinhole {
                f: [params[0], params[0], params[1] - c, params[2] - c],
            }
        }
        "PINHOLE" => {
            count(4, "fx, fy, cx, cy")?;
            Model::Pinhole {
                f: [params[0], params[1], params[2] - c, params[3] - c],
            }
        }
        "SIMPLE_RADIAL" => {
            count(4, "f, cx, cy, k")?;
            Model::radtan(
                [params[0], params[0], params[1] - c, params[2] - c],
                [params[3], 0.0, 0.0],
                [0.0, 0.0],
            )
        }
        "RADIAL" => {
            count(5, "f, cx, cy, k1, k2")?;
            Model::radtan(
                [params[0], params[0], params[1] - c, params[2] - c],
                [params[3], params[4], 0.0],
                [0.0, 0.0],
            )
        }
        "OPENCV" => {
            count(8, "fx, fy, cx, cy, k1, k2, p1, p2")?;
            Model::radtan(
                [params[0], params[1], params[2] - c, params[3] - c],
                [params[4], params[5], 0.0],
                [params[6], params[7]],
            )
        }
        "FULL_OPENCV" => {
            count(12, "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6")?;
            Model::RadTan {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                k: [
                    params[4], params[5], params[8], params[9], params[10], params[11],
                ],
                p: [params[6], params[7]],
                rpmax: 0.0,
            }
        }
        "FOV" => {
            count(5, "fx, fy, cx, cy, omega")?;
            Model::Fov {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                w: params[4],
            }
        }
        "OPENCV_FISHEYE" => {
            count(8, "fx, fy, cx, cy, k1, k2, k3, k4")?;
            Model::KannalaBrandt {
                f: [params[0], params[1], params[2] - c, params[3] - c],
                k: [params[4], params[5], params[6], params[7]],
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
