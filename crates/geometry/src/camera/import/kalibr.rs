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
        // Kalibr's intrinsics: the projection's own parameters, then `[fu, fv, pu, pv]`; checked
        // to be the `n` values `what` and split there.
        let ints = |n: usize, what: &str| -> Result<(&[f64], [f64; 4])> {
            expect_len(intrinsics, n, path, &field("intrinsics"), what)?;
            let (params, f) = intrinsics.split_at(n - 4);
            Ok((params, [f[0], f[1], f[2], f[3]]))
        };
        let coefs =
            |n: usize, what: &str| expect_len(coeffs, n, path, &field("distortion_coeffs"), what);
        let zero_coeffs = coeffs.iter().all(|c| *c == 0.0);
        let name = self.name();
        Ok(match (camera_model, distortion) {
            ("pinhole", "equidistant") => {
                let (_, f) = ints(4, "[fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, k3, k4]")?;
                Model::KannalaBrandt {
                    f,
                    k: [coeffs[0], coeffs[1], coeffs[2], coeffs[3]],
                }
            }
            ("pinhole", "radtan") => {
                let (_, f) = ints(4, "[fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, p1, p2]")?;
                notes.push("k3 = 0: Kalibr's radtan has four coefficients".to_string());
                Model::radtan(f, [coeffs[0], coeffs[1], 0.0], [coeffs[2], coeffs[3]])
            }
            ("pinhole", "fov") => {
                let (_, f) = ints(4, "[fu, fv, pu, pv]")?;
                coefs(1, "[w]")?;
                Model::Fov { f, w: coeffs[0] }
            }
            ("omni", "radtan") if !zero_coeffs => {
                let (params, f) = ints(5, "[xi, fu, fv, pu, pv]")?;
                coefs(4, "[k1, k2, p1, p2]")?;
                Model::Mei {
                    f,
                    xi: params[0],
                    k: [coeffs[0], coeffs[1]],
                    p: [coeffs[2], coeffs[3]],
                }
            }
            ("pinhole", "none") => Model::Pinhole {
                f: ints(4, "[fu, fv, pu, pv]")?.1,
            },
            ("ds", "none") => {
                let (params, f) = ints(6, "[xi, alpha, fu, fv, pu, pv]")?;
                Model::DoubleSphere {
                    f,
                    xi: params[0],
                    alpha: params[1],
                }
            }
            ("eucm", "none") => {
                let (params, f) = ints(6, "[alpha, beta, fu, fv, pu, pv]")?;
                Model::ExtendedUnified {
                    f,
                    alpha: params[0],
                    beta: params[1],
                }
            }
            ("omni", "none") | ("omni", "radtan") if zero_coeffs => {
                let (params, [fu, fv, pu, pv]) = ints(5, "[xi, fu, fv, pu, pv]")?;
                let xi = params[0];
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
                    f: [fu / (1.0 + xi), fv / (1.0 + xi), pu, pv],
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
