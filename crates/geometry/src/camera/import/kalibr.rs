//! Kalibr camchain YAML (`camN:` blocks).

use std::path::Path;

use serde_json::Value;

use super::tree::{expect_len, get, numbers, parse_tree, size_pair};
use super::{camera_error, ImportOptions, Model, Parsed};
use crate::error::Result;

const KALIBR_SUPPORTED: &str = "pinhole-equi, pinhole-radtan, pinhole-fov, pinhole-none, \
     omni-radtan, omni-none, ds-none, eucm-none";

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    let n = options.camera.unwrap_or(0);
    let key = format!("cam{n}");
    let cam = tree.get(&key).ok_or_else(|| {
        let found: Vec<&String> = tree
            .as_object()
            .map(|o| o.keys().filter(|k| k.starts_with("cam")).collect())
            .unwrap_or_default();
        camera_error(
            path,
            &key,
            format!("no such camera in the camchain (found: {found:?}); choose with --camera"),
        )
    })?;
    let field = |name: &str| format!("{key}.{name}");
    let camera_model = get(cam, "camera_model", path, &field("camera_model"))?
        .as_str()
        .unwrap_or_default()
        .to_string();
    let distortion = match cam.get("distortion_model") {
        None | Some(Value::Null) => "none".to_string(),
        Some(v) => v.as_str().unwrap_or_default().to_string(),
    };
    let intrinsics = numbers(
        get(cam, "intrinsics", path, &field("intrinsics"))?,
        path,
        &field("intrinsics"),
    )?;
    let coeffs = match cam.get("distortion_coeffs") {
        None | Some(Value::Null) => Vec::new(),
        Some(v) => numbers(v, path, &field("distortion_coeffs"))?,
    };
    let size = size_pair(
        get(cam, "resolution", path, &field("resolution"))?,
        path,
        &field("resolution"),
    )?;
    let entry = Entry {
        key: &key,
        camera_model: &camera_model,
        distortion: &distortion,
        intrinsics: &intrinsics,
        coeffs: &coeffs,
    };
    let mut notes = Vec::new();
    let model = entry.model(path, &mut notes)?;
    Ok(Parsed {
        model,
        size,
        source: format!("kalibr {key} ({})", entry.name()),
        notes,
    })
}

/// One `camN` block of a camchain, as read.
struct Entry<'a> {
    key: &'a str,
    camera_model: &'a str,
    distortion: &'a str,
    intrinsics: &'a [f64],
    coeffs: &'a [f64],
}

impl Entry<'_> {
    /// Kalibr's name of the model, `camera_model-distortion` (`pinhole-equi`).
    fn name(&self) -> String {
        let short = match self.distortion {
            "equidistant" => "equi",
            other => other,
        };
        format!("{}-{short}", self.camera_model)
    }

    /// The model of the block; `notes` gets one line per convention converted.
    fn model(&self, path: &Path, notes: &mut Vec<String>) -> Result<Model> {
        let (camera_model, distortion) = (self.camera_model, self.distortion);
        let (intrinsics, coeffs) = (self.intrinsics, self.coeffs);
        let field = |name: &str| format!("{}.{name}", self.key);
        let ints =
            |n: usize, what: &str| expect_len(intrinsics, n, path, &field("intrinsics"), what);
        let coefs =
            |n: usize, what: &str| expect_len(coeffs, n, path, &field("distortion_coeffs"), what);
        let zero_coeffs = coeffs.iter().all(|c| *c == 0.0);
        let name = self.name();
        Ok(match (camera_model, distortion) {
            ("pinhole", "equidistant") => {
                ints(4, "[fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, k3, k4]")?;
                Model::KannalaBrandt {
                    f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                    k: [coeffs[0], coeffs[1], coeffs[2], coeffs[3]],
                }
            }
            ("pinhole", "radtan") => {
                ints(4, "[fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, p1, p2]")?;
                notes.push("k3 = 0: Kalibr's radtan has four coefficients".to_string());
                Model::radtan(
                    [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                    [coeffs[0], coeffs[1], 0.0],
                    [coeffs[2], coeffs[3]],
                )
            }
            ("pinhole", "fov") => {
                ints(4, "[fu, fv, pu, pv]")?;
                coefs(1, "[w]")?;
                Model::Fov {
                    f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                    w: coeffs[0],
                }
            }
            ("omni", "radtan") if !zero_coeffs => {
                ints(5, "[xi, fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, p1, p2]")?;
                Model::Mei {
                    f: [intrinsics[1], intrinsics[2], intrinsics[3], intrinsics[4]],
                    xi: intrinsics[0],
                    k: [coeffs[0], coeffs[1]],
                    p: [coeffs[2], coeffs[3]],
                }
            }
            ("pinhole", "none") => {
                ints(4, "[fu, fv, pu, pv]")?;
                Model::Pinhole {
                    f: [intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]],
                }
            }
            ("ds", "none") => {
                ints(6, "[xi, alpha, fu, fv, pu, pv]")?;
                Model::DoubleSphere {
                    f: [intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]],
                    xi: intrinsics[0],
                    alpha: intrinsics[1],
                }
            }
            ("eucm", "none") => {
                ints(6, "[alpha, beta, fu, fv, pu, pv]")?;
                Model::ExtendedUnified {
                    f: [intrinsics[2], intrinsics[3], intrinsics[4], intrinsics[5]],
                    alpha: intrinsics[0],
                    beta: intrinsics[1],
                }
            }
            ("omni", "none") | ("omni", "radtan") if zero_coeffs => {
                ints(5, "[xi, fu, fv, pu, pv]")?;
                let xi = intrinsics[0];
                if xi.is_nan() || xi <= -1.0 {
                    return Err(camera_error(
                        path,
                        &field("intrinsics"),
                        format!("omni xi = {xi} must be > -1"),
                    ));
                }
                notes.push(format!(
                    "Kalibr omni (Mei, xi = {xi:?}) as the unified model: alpha = xi / (1 + xi), \
                 fx = fu / (1 + xi), fy = fv / (1 + xi)"
                ));
                Model::Unified {
                    f: [
                        intrinsics[1] / (1.0 + xi),
                        intrinsics[2] / (1.0 + xi),
                        intrinsics[3],
                        intrinsics[4],
                    ],
                    alpha: xi / (1.0 + xi),
                }
            }
            _ => {
                return Err(camera_error(
                    path,
                    &field("camera_model"),
                    format!(
                        "Kalibr model `{name}` is not supported (supported: {KALIBR_SUPPORTED})"
                    ),
                ));
            }
        })
    }
}
