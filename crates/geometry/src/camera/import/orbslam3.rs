//! ORB-SLAM3 settings files (`%YAML:1.0` or `%YAML 1.0`, `cv::FileStorage`).
//!
//! `Camera.type` is `"PinHole"` (radial-tangential `k1 k2 p1 p2`, optional `k3`),
//! `"KannalaBrandt8"` (`k1..k4`, OpenCV's fisheye polynomial) or `"Rectified"` (no distortion).
//! Two spellings of the keys:
//! - older files: `Camera.fx`, `Camera.fy`, `Camera.cx`, `Camera.cy`, `Camera.k1` ..., and for a
//!   second camera of a stereo rig `Camera2.fx` ...;
//! - settings version 1.0 (`File.version: "1.0"`): `Camera1.fx` ... and `Camera2.fx` ...
//!
//! Both give the image size as `Camera.width` and `Camera.height`. `--camera 0` (the default) is
//! the first camera (`Camera1`, or `Camera` in older files), `--camera 1` the second (`Camera2`),
//! with its own coefficients: numbered like Kalibr's `cam0` / `cam1`, from which ORB-SLAM3's
//! rig files are usually written.

use std::path::Path;

use serde_json::Value;

use super::tree::{dimension, get, number, parse_tree};
use super::{camera_error, format_error, ImportOptions, Model, Parsed};
use crate::error::Result;

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    if !tree.is_object() {
        return Err(format_error(path, "expected a map of settings".to_string()));
    }
    let new_keys = tree.get("Camera1.fx").is_some() || tree.get("File.version").is_some();
    let n = options.camera.unwrap_or(0);
    let prefix = match (n, new_keys) {
        (0, true) => "Camera1",
        (0, false) => "Camera",
        (1, _) => "Camera2",
        _ => {
            return Err(format_error(
                path,
                format!(
                    "--camera {n}: ORB-SLAM3 settings hold at most two cameras, 0 (Camera1, or \
                     Camera in older files) and 1 (Camera2)"
                ),
            ))
        }
    };
    let type_field = "Camera.type";
    let camera_type = match get(&tree, type_field, path, type_field)? {
        Value::String(s) => s.clone(),
        other => {
            return Err(camera_error(
                path,
                type_field,
                format!("expected a name, found {other}"),
            ))
        }
    };
    if n == 1 && tree.get("Camera2.fx").is_none() {
        return Err(camera_error(
            path,
            "Camera2.fx",
            "--camera 1: the file has no second camera".to_string(),
        ));
    }
    let p = |name: &str| {
        let key = format!("{prefix}.{name}");
        number(get(&tree, &key, path, &key)?, path, &key)
    };
    let optional = |name: &str| -> Result<f64> {
        match tree.get(format!("{prefix}.{name}").as_str()) {
            Some(_) => p(name),
            None => Ok(0.0),
        }
    };
    let f = [p("fx")?, p("fy")?, p("cx")?, p("cy")?];
    let mut notes = Vec::new();
    let model = match camera_type.as_str() {
        "PinHole" => {
            if tree.get(format!("{prefix}.k3").as_str()).is_none() {
                notes.push(format!("k3 = 0: the file has no {prefix}.k3"));
            }
            Model::radtan(
                f,
                [p("k1")?, p("k2")?, optional("k3")?],
                [p("p1")?, p("p2")?],
            )
        }
        "KannalaBrandt8" => Model::KannalaBrandt {
            f,
            k: [p("k1")?, p("k2")?, p("k3")?, p("k4")?],
        },
        "Rectified" => Model::Pinhole { f },
        other => {
            return Err(camera_error(
                path,
                type_field,
                format!(
                    "ORB-SLAM3 camera type `{other}` is not supported (supported: PinHole, \
                     KannalaBrandt8, Rectified)"
                ),
            ))
        }
    };
    let size = [
        dimension(
            get(&tree, "Camera.width", path, "Camera.width")?,
            path,
            "Camera.width",
        )?,
        dimension(
            get(&tree, "Camera.height", path, "Camera.height")?,
            path,
            "Camera.height",
        )?,
    ];
    Ok(Parsed {
        model,
        size,
        source: format!("orbslam3 {prefix} ({camera_type})"),
        notes,
    })
}
