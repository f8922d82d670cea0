//! OpenCV calibration files: `cv::FileStorage` YAML (`%YAML:1.0`, `!!opencv-matrix`), XML
//! (`<opencv_storage>`, `type_id="opencv-matrix"`) or JSON, or plain YAML / JSON. Keys are
//! matched without regard to case, so the calibration sample's older spellings
//! (`Camera_Matrix`, `Distortion_Coefficients`, `image_Width`, `image_Height`) read too.

use std::path::Path;

use serde_json::Value;

use super::tree::{dimension, expect_len, number, numbers, parse_tree, size_pair};
use super::{camera_error, ImportOptions, Model, OpenCvModel, Parsed};
use crate::error::Result;

const OPENCV_K_KEYS: [&str; 4] = ["camera_matrix", "cameraMatrix", "K", "intrinsic_matrix"];
const OPENCV_D_KEYS: [&str; 5] = [
    "distortion_coefficients",
    "dist_coeffs",
    "distCoeffs",
    "D",
    "distortion",
];

/// The first of `keys` present in `tree` (compared without regard to case), with its name as
/// the file spells it.
pub(super) fn first_key<'a>(tree: &'a Value, keys: &[&str]) -> Option<(&'a str, &'a Value)> {
    let object = tree.as_object()?;
    keys.iter().find_map(|k| {
        object
            .iter()
            .find(|(name, _)| name.eq_ignore_ascii_case(k))
            .map(|(name, v)| (name.as_str(), v))
    })
}

/// A matrix as OpenCV's FileStorage writes it (`{rows, cols, dt, data}`, tagged
/// `!!opencv-matrix` in YAML, `"type_id": "opencv-matrix"` in JSON), a nested list, or a flat
/// list: its values in row-major order.
pub(super) fn matrix(v: &Value, path: &Path, field: &str) -> Result<Vec<f64>> {
    match v {
        Value::Object(m) => {
            let data = numbers(
                m.get("data")
                    .ok_or_else(|| camera_error(path, field, "matrix without `data`".into()))?,
                path,
                &format!("{field}.data"),
            )?;
            if let (Some(r), Some(c)) = (m.get("rows"), m.get("cols")) {
                let (r, c) = (number(r, path, field)?, number(c, path, field)?);
                if r * c != data.len() as f64 {
                    return Err(camera_error(
                        path,
                        field,
                        format!("{r}x{c} matrix with {} values", data.len()),
                    ));
                }
            }
            Ok(data)
        }
        Value::Array(rows) if rows.iter().all(|r| r.is_array()) => {
            let mut out = Vec::new();
            for (i, row) in rows.iter().enumerate() {
                out.extend(numbers(row, path, &format!("{field}[{i}]"))?);
            }
            Ok(out)
        }
        other => numbers(other, path, field),
    }
}

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    let f = focal_and_centre(&tree, path)?;
    let (d_key, d_value) = first_key(&tree, &OPENCV_D_KEYS).ok_or_else(|| {
        camera_error(
            path,
            "distortion_coefficients",
            format!("no distortion coefficients (looked for {OPENCV_D_KEYS:?})"),
        )
    })?;
    let d = matrix(d_value, path, d_key)?;
    let size = image_size(&tree, path)?;
    // Which model: the command line, then the file, then the number of coefficients.
    let from_file = declared_model(&tree, path)?;
    let model = match options.opencv_model.or(from_file) {
        Some(m) => m,
        None if d.len() == 4 => {
            return Err(camera_error(
                path,
                d_key,
                "4 coefficients fit both OpenCV's fisheye model (k1..k4) and the standard one \
                 (k1 k2 p1 p2), and the file does not say which: pass --opencv-model fisheye or \
                 --opencv-model standard"
                    .to_string(),
            ))
        }
        None => OpenCvModel::Standard,
    };
    let mut notes = Vec::new();
    let read = Coefficients {
        f,
        d: &d,
        key: d_key,
        path,
    };
    let (model, name) = coefficients(model, &read, &mut notes)?;
    Ok(Parsed {
        model,
        size,
        source: format!("opencv ({name} model)"),
        notes,
    })
}

/// `[fx, fy, cx, cy]` of the file's camera matrix, which must be `[[fx, 0, cx], [0, fy, cy],
/// [0, 0, 1]]`.
pub(super) fn focal_and_centre(tree: &Value, path: &Path) -> Result<[f64; 4]> {
    let (k_key, k_value) = first_key(tree, &OPENCV_K_KEYS).ok_or_else(|| {
        camera_error(
            path,
            "camera_matrix",
            format!("no camera matrix (looked for {OPENCV_K_KEYS:?})"),
        )
    })?;
    let k = matrix(k_value, path, k_key)?;
    expect_len(&k, 9, path, k_key, "a 3x3 camera matrix")?;
    camera_matrix_entries(&k, path, k_key)?;
    Ok([k[0], k[4], k[2], k[5]])
}

/// Checks a row-major 3x3 camera matrix `k` (read from `field`) is `[[fx, 0, cx], [0, fy, cy],
/// [0, 0, 1]]`. Skew (`k[0][1]`) is refused: no model of this crate has it, and dropping it
/// would move every pixel by up to `skew * y'` (the error names the entry).
pub(super) fn camera_matrix_entries(k: &[f64], path: &Path, field: &str) -> Result<()> {
    if k[1] != 0.0 {
        return Err(camera_error(
            path,
            &format!("{field}[0][1]"),
            format!(
                "a skewed camera matrix (skew = {}) is not supported: the camera models here \
                 have u = fx x'' + cx; recalibrate with zero skew (OpenCV's default)",
                k[1]
            ),
        ));
    }
    for (i, want) in [(3, 0.0), (6, 0.0), (7, 0.0), (8, 1.0)] {
        if k[i] != want {
            return Err(camera_error(
                path,
                &format!("{field}[{}][{}]", i / 3, i % 3),
                format!(
                    "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], found {} here ({k:?})",
                    k[i]
                ),
            ));
        }
    }
    Ok(())
}

/// Distortion coefficients as read: the values `d` of the key `key` of the file `path`, with the
/// `[fx, fy, cx, cy]` of the camera they belong to. What the readers of OpenCV's and ROS's
/// models pass around; errors name `key` (or one of its entries) in `path`.
pub(super) struct Coefficients<'a> {
    pub f: [f64; 4],
    pub d: &'a [f64],
    pub key: &'a str,
    pub path: &'a Path,
}

/// The model of the distortion coefficients for OpenCV's `model`, and its name; `notes` gets a
/// line per convention converted.
pub(super) fn coefficients(
    model: OpenCvModel,
    read: &Coefficients<'_>,
    notes: &mut Vec<String>,
) -> Result<(Model, &'static str)> {
    Ok(match model {
        OpenCvModel::Fisheye => (fisheye(read, "fisheye [k1, k2, k3, k4]")?, "fisheye"),
        OpenCvModel::Standard => (standard(read, notes)?, "standard"),
    })
}

/// OpenCV's fisheye model (Kannala-Brandt) of `d` = `k1 k2 k3 k4`; `what` names the model in
/// the error for another count.
pub(super) fn fisheye(read: &Coefficients<'_>, what: &str) -> Result<Model> {
    let Coefficients { f, d, key, path } = *read;
    expect_len(d, 4, path, key, what)?;
    Ok(Model::KannalaBrandt {
        f,
        k: [d[0], d[1], d[2], d[3]],
    })
}

/// OpenCV's standard model of `d` = `k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]`: the
/// 5-coefficient or rational model; thin-prism and tilt terms must be zero.
pub(super) fn standard(read: &Coefficients<'_>, notes: &mut Vec<String>) -> Result<Model> {
    let Coefficients {
        f,
        d,
        key: d_key,
        path,
    } = *read;
    if ![4, 5, 8, 12, 14].contains(&d.len()) {
        return Err(camera_error(
            path,
            d_key,
            format!(
                "OpenCV's standard model has 4, 5, 8, 12 or 14 coefficients, found {}",
                d.len()
            ),
        ));
    }
    if let Some(i) = (8..d.len()).find(|&i| d[i] != 0.0) {
        return Err(camera_error(
            path,
            &format!("{d_key}[{i}]"),
            format!(
                "OpenCV's thin-prism / tilted model (non-zero s1..s4, tx, ty of {} coefficients) \
                 is not supported; the rational model k1 k2 p1 p2 k3 k4 k5 k6 is",
                d.len()
            ),
        ));
    }
    if d.len() == 4 {
        notes.push("k3 = 0: the file has four coefficients".to_string());
    }
    let at = |i: usize| d.get(i).copied().unwrap_or(0.0);
    Ok(Model::RadTan {
        f,
        k: [d[0], d[1], at(4), at(5), at(6), at(7)],
        p: [d[2], d[3]],
        rpmax: 0.0,
    })
}

/// `image_width` + `image_height`, or a two-element `image_size` / `imageSize` / `resolution`.
fn image_size(tree: &Value, path: &Path) -> Result<[usize; 2]> {
    Ok(
        if let (Some((wk, w)), Some((hk, h))) = (
            first_key(tree, &["image_width"]),
            first_key(tree, &["image_height"]),
        ) {
            [dimension(w, path, wk)?, dimension(h, path, hk)?]
        } else if let Some((key, v)) = first_key(tree, &["image_size", "imageSize", "resolution"]) {
            let values = matrix(v, path, key)?;
            expect_len(&values, 2, path, key, "[width, height]")?;
            let pair = Value::from(values);
            size_pair(&pair, path, key)?
        } else {
            return Err(camera_error(
                path,
                "image_width",
                "no image size (looked for image_width + image_height, image_size, imageSize, \
             resolution)"
                    .to_string(),
            ));
        },
    )
}

/// The model the file declares (`fisheye_model: 0 | 1`, or `distortion_model` / `model` by
/// name), if it does.
fn declared_model(tree: &Value, path: &Path) -> Result<Option<OpenCvModel>> {
    Ok(if let Some((_, v)) = first_key(tree, &["fisheye_model"]) {
        // OpenCV's camera_calibration sample writes `fisheye_model: 0 | 1`.
        match v {
            Value::Bool(b) => Some(*b),
            other => Some(number(other, path, "fisheye_model")? != 0.0),
        }
        .map(|fisheye| {
            if fisheye {
                OpenCvModel::Fisheye
            } else {
                OpenCvModel::Standard
            }
        })
    } else if let Some((key, v)) = first_key(tree, &["distortion_model", "model"]) {
        match v.as_str().unwrap_or_default() {
            "fisheye" | "equidistant" | "kannala_brandt" | "kannala-brandt" => {
                Some(OpenCvModel::Fisheye)
            }
            "plumb_bob"
            | "rational_polynomial"
            | "radtan"
            | "radial-tangential"
            | "standard"
            | "pinhole" => Some(OpenCvModel::Standard),
            other => {
                return Err(camera_error(
                    path,
                    key,
                    format!(
                        "OpenCV model `{other}` is not supported (supported: fisheye, \
                         equidistant, plumb_bob, rational_polynomial, radtan)"
                    ),
                ))
            }
        }
    } else {
        None
    })
}
