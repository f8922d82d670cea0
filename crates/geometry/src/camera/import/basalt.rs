//! Basalt calibration JSON (`value0.intrinsics[N]`).

use std::path::Path;

use super::tree::{get, number, parse_tree, size_pair};
use super::{camera_error, ImportOptions, Model, Parsed};
use crate::error::Result;

pub(super) fn read(text: &str, path: &Path, options: &ImportOptions) -> Result<Parsed> {
    let tree = parse_tree(text, path)?;
    // cereal wraps the object in `value0`.
    let root = tree.get("value0").unwrap_or(&tree);
    let n = options.camera.unwrap_or(0);
    let list = get(root, "intrinsics", path, "value0.intrinsics")?
        .as_array()
        .ok_or_else(|| camera_error(path, "value0.intrinsics", "expected a list".into()))?;
    let field = format!("value0.intrinsics[{n}]");
    let entry = list.get(n).ok_or_else(|| {
        camera_error(
            path,
            &field,
            format!(
                "the file has {} camera(s); choose with --camera",
                list.len()
            ),
        )
    })?;
    let camera_type = get(entry, "camera_type", path, &format!("{field}.camera_type"))?
        .as_str()
        .unwrap_or_default()
        .to_string();
    let params = get(entry, "intrinsics", path, &format!("{field}.intrinsics"))?;
    let p = |name: &str| {
        let f = format!("{field}.intrinsics.{name}");
        number(get(params, name, path, &f)?, path, &f)
    };
    let resolution = get(root, "resolution", path, "value0.resolution")?;
    let size = match resolution.as_array().and_then(|r| r.get(n)) {
        Some(pair) => size_pair(pair, path, &format!("value0.resolution[{n}]"))?,
        None => {
            return Err(camera_error(
                path,
                "value0.resolution",
                format!("no resolution for camera {n}"),
            ))
        }
    };
    let f = || -> Result<[f64; 4]> { Ok([p("fx")?, p("fy")?, p("cx")?, p("cy")?]) };
    let model = match camera_type.as_str() {
        "kb4" => Model::KannalaBrandt {
            f: f()?,
            k: [p("k1")?, p("k2")?, p("k3")?, p("k4")?],
        },
        "ds" => Model::DoubleSphere {
            f: f()?,
            xi: p("xi")?,
            alpha: p("alpha")?,
        },
        "eucm" => Model::ExtendedUnified {
            f: f()?,
            alpha: p("alpha")?,
            beta: p("beta")?,
        },
        "ucm" => Model::Unified {
            f: f()?,
            alpha: p("alpha")?,
        },
        "pinhole" => Model::Pinhole { f: f()? },
        "pinhole-radtan8" => Model::RadTan {
            f: f()?,
            k: [p("k1")?, p("k2")?, p("k3")?, p("k4")?, p("k5")?, p("k6")?],
            p: [p("p1")?, p("p2")?],
            rpmax: match params.get("rpmax") {
                Some(_) => p("rpmax")?,
                None => 0.0,
            },
        },
        "fov" => Model::Fov {
            f: f()?,
            w: p("w")?,
        },
        other => {
            return Err(camera_error(
                path,
                &format!("{field}.camera_type"),
                format!(
                    "Basalt camera type `{other}` is not supported (supported: kb4, ds, eucm, \
                     ucm, pinhole, pinhole-radtan8, fov)"
                ),
            ))
        }
    };
    Ok(Parsed {
        model,
        size,
        source: format!("basalt intrinsics[{n}] ({camera_type})"),
        notes: Vec::new(),
    })
}
