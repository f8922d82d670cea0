//! ROS `camera_calibration` results: `ost.yaml` (the `sensor_msgs/CameraInfo` YAML of
//! `camera_calibration_parsers`) and `ost.txt` (its INI-like text form).
//!
//! `ost.yaml`: `image_width`, `image_height`, `camera_matrix {rows, cols, data}`,
//! `distortion_model` (`plumb_bob`, `rational_polynomial` or `equidistant`),
//! `distortion_coefficients {rows, cols, data}`; the rectification and projection matrices
//! describe the rectified image and are not read (the camera matrix is the camera's).
//!
//! `ost.txt`: sections `[image]` (`width`, `height`, each name on its own line and the value on
//! the next) and `[camera_name]` (`camera matrix`: three rows; `distortion`: one row;
//! `rectification`, `projection`). It does not name the distortion model: 5 coefficients are
//! `plumb_bob`, 8 `rational_polynomial`, 4 `equidistant` (what the fisheye calibration
//! writes). A stereo calibration's `ost.txt` holds one `[image]` + camera block per camera:
//! `--camera N` picks the N-th (default 0).

use std::path::Path;

use serde_json::Value;

use super::opencv::{
    camera_matrix_entries, first_key, fisheye, focal_and_centre, matrix, standard, Coefficients,
};
use super::tree::{dimension, expect_len, parse_float, parse_tree};
use super::{camera_error, format_error, ImportOptions, Model, Parsed};
use crate::error::Result;

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let body = text.trim_start_matches('\u{feff}');
    let ini = body
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .is_some_and(|l| l.starts_with('['));
    if ini {
        read_txt(body, path, options)
    } else {
        if options.camera.is_some_and(|n| n != 0) {
            return Err(format_error(
                path,
                "--camera: an ost.yaml holds one camera (0)".to_string(),
            ));
        }
        read_yaml(body, path)
    }
}

fn read_yaml(text: &str, path: &Path) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    let f = focal_and_centre(&tree, path)?;
    let (w, h) = match (
        first_key(&tree, &["image_width"]),
        first_key(&tree, &["image_height"]),
    ) {
        (Some((wk, w)), Some((hk, h))) => (dimension(w, path, wk)?, dimension(h, path, hk)?),
        _ => {
            return Err(camera_error(
                path,
                "image_width",
                "missing image_width / image_height".to_string(),
            ))
        }
    };
    let (d_key, d_value) = first_key(&tree, &["distortion_coefficients"])
        .ok_or_else(|| camera_error(path, "distortion_coefficients", "missing".to_string()))?;
    let d = matrix(d_value, path, d_key)?;
    let model_name = match first_key(&tree, &["distortion_model"]) {
        Some((_, Value::String(s))) => s.clone(),
        Some((key, other)) => {
            return Err(camera_error(
                path,
                key,
                format!("expected a name, found {other}"),
            ))
        }
        None => {
            return Err(camera_error(
                path,
                "distortion_model",
                "missing (plumb_bob, rational_polynomial or equidistant)".to_string(),
            ))
        }
    };
    let mut notes = Vec::new();
    let read = Coefficients {
        f,
        d: &d,
        key: d_key,
        path,
    };
    let model = distortion(&model_name, &read, &mut notes)?;
    let name = match first_key(&tree, &["camera_name"]) {
        Some((_, Value::String(s))) => format!(" {s}"),
        _ => String::new(),
    };
    Ok(Parsed {
        model,
        size: [w, h],
        source: format!("ros ost.yaml{name} ({model_name})"),
        notes,
    })
}

/// The model of ROS's `distortion_model` `name` with the coefficients `read`.
fn distortion(name: &str, read: &Coefficients<'_>, notes: &mut Vec<String>) -> Result<Model> {
    let Coefficients { d, key, path, .. } = *read;
    match name {
        "plumb_bob" | "rational_polynomial" => {
            let n = if name == "plumb_bob" { 5 } else { 8 };
            if !(d.len() == n || (name == "plumb_bob" && d.len() == 4)) {
                expect_len(d, n, path, key, name)?;
            }
            standard(read, notes)
        }
        "equidistant" => fisheye(read, "equidistant [k1, k2, k3, k4]"),
        other => Err(camera_error(
            path,
            "distortion_model",
            format!(
                "ROS distortion model `{other}` is not supported (supported: plumb_bob, \
                 rational_polynomial, equidistant)"
            ),
        )),
    }
}

/// One camera block of an `ost.txt`: its section name, the size of the `[image]` before it, and
/// its keys with the numbers under each (with the line of the key).
struct Block {
    name: String,
    size: Option<[usize; 2]>,
    keys: Vec<(String, usize, Vec<f64>)>,
}

fn read_txt(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let blocks = txt_blocks(text, path)?;
    let n = options.camera.unwrap_or(0);
    let block = blocks.get(n).ok_or_else(|| {
        let names: Vec<&str> = blocks.iter().map(|b| b.name.as_str()).collect();
        format_error(
            path,
            format!(
                "no camera {n} in the file (its camera sections: {names:?}); choose with --camera"
            ),
        )
    })?;
    let section = |key: &str| format!("[{}] {key}", block.name);
    let get = |key: &str| -> Result<&Vec<f64>> {
        block
            .keys
            .iter()
            .find(|(k, _, _)| k == key)
            .map(|(_, _, v)| v)
            .ok_or_else(|| camera_error(path, &section(key), "missing".to_string()))
    };
    let size = block.size.ok_or_else(|| {
        camera_error(
            path,
            "[image] width",
            "no [image] section with width and height before the camera".to_string(),
        )
    })?;
    let k = get("camera matrix")?;
    let k_field = section("camera matrix");
    expect_len(k, 9, path, &k_field, "a 3x3 camera matrix")?;
    camera_matrix_entries(k, path, &k_field)?;
    let f = [k[0], k[4], k[2], k[5]];
    let d = get("distortion")?;
    let d_field = section("distortion");
    let model_name = match d.len() {
        4 => "equidistant",
        8 => "rational_polynomial",
        _ => "plumb_bob",
    };
    let mut notes = Vec::new();
    if d.len() == 4 {
        notes.push(
            "equidistant (Kannala-Brandt): ost.txt does not name the model, and 4 coefficients \
             are what ROS's fisheye calibration writes (plumb_bob writes 5)"
                .to_string(),
        );
    }
    let read = Coefficients {
        f,
        d,
        key: &d_field,
        path,
    };
    let model = distortion(model_name, &read, &mut notes)?;
    Ok(Parsed {
        model,
        size,
        source: format!("ros ost.txt [{}] ({model_name})", block.name),
        notes,
    })
}

/// The camera blocks of an `ost.txt` (module docs), in file order.
fn txt_blocks(text: &str, path: &Path) -> Result<Vec<Block>> {
    let mut blocks: Vec<Block> = Vec::new();
    let mut image: Vec<(String, usize, Vec<f64>)> = Vec::new();
    let mut in_image = false;
    let mut size = None;
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if let Some(name) = line.strip_prefix('[') {
            let name = name.strip_suffix(']').ok_or_else(|| {
                format_error(path, format!("line {}: a section name without `]`", i + 1))
            })?;
            in_image = name == "image";
            if in_image {
                image.clear();
                size = None;
            } else {
                blocks.push(Block {
                    name: name.to_string(),
                    size,
                    keys: Vec::new(),
                });
            }
            continue;
        }
        let numbers: Option<Vec<f64>> = line.split_whitespace().map(parse_float).collect();
        let keys = if in_image {
            &mut image
        } else {
            match blocks.last_mut() {
                Some(b) => &mut b.keys,
                None => {
                    return Err(format_error(
                        path,
                        format!("line {}: `{line}` outside any section", i + 1),
                    ))
                }
            }
        };
        match numbers {
            Some(values) => match keys.last_mut() {
                Some((_, _, v)) => v.extend(values),
                None => {
                    return Err(format_error(
                        path,
                        format!("line {}: numbers before any key", i + 1),
                    ))
                }
            },
            None => keys.push((line.to_string(), i + 1, Vec::new())),
        }
        if in_image {
            size = image_size(&image, path)?;
        }
    }
    Ok(blocks)
}

/// `[width, height]` once both are in the `[image]` section.
fn image_size(keys: &[(String, usize, Vec<f64>)], path: &Path) -> Result<Option<[usize; 2]>> {
    let value = |name: &str| keys.iter().find(|(k, _, _)| k == name);
    let (Some(w), Some(h)) = (value("width"), value("height")) else {
        return Ok(None);
    };
    let mut out = [0; 2];
    for (slot, (key, line, v)) in out.iter_mut().zip([w, h]) {
        let field = format!("line {line}: [image] {key}");
        match v.as_slice() {
            [] => return Ok(None),
            [x] => *slot = dimension(&Value::from(*x), path, &field)?,
            _ => {
                return Err(camera_error(
                    path,
                    &field,
                    format!("expected one number, found {}", v.len()),
                ))
            }
        }
    }
    Ok(Some(out))
}
