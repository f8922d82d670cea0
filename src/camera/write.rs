//! Writing cameras back to the TOML file format of [`super::file`] (`data/cameras/*.toml`).
//!
//! Floats are written with Rust's shortest round-trip representation (`{:?}`), so
//! `load(to_toml(cam)) == cam` exactly; field names and order follow the shipped files.

use std::fmt::Write as _;

use super::Camera;

impl Camera {
    /// The camera as the text of a camera file (named fields, no comments); `name` and
    /// `description` are written when given. Reading it back gives an equal camera.
    pub fn to_toml(&self, name: Option<&str>, description: Option<&str>) -> String {
        let mut out = String::new();
        // Quoted with TOML basic-string escapes (Rust's Debug escapes are a superset that TOML
        // accepts for the characters a name can reasonably hold).
        if let Some(n) = name {
            let _ = writeln!(out, "name = {}", toml_string(n));
        }
        if let Some(d) = description {
            let _ = writeln!(out, "description = {}", toml_string(d));
        }
        match self {
            Camera::KannalaBrandt(m) => {
                let _ = writeln!(out, "model = \"kannala-brandt\"");
                let _ = writeln!(out, "width = {}", m.width);
                let _ = writeln!(out, "height = {}", m.height);
                let _ = writeln!(out, "fov_deg = {:?}", m.fov_deg);
                for (k, v) in [("fx", m.fx), ("fy", m.fy), ("cx", m.cx), ("cy", m.cy)] {
                    let _ = writeln!(out, "{k} = {v:?}");
                }
                for (i, v) in m.k.iter().enumerate() {
                    let _ = writeln!(out, "k{} = {v:?}", i + 1);
                }
            }
            Camera::Pinhole(m) => {
                let _ = writeln!(out, "model = \"pinhole\"");
                let _ = writeln!(out, "width = {}", m.width);
                let _ = writeln!(out, "height = {}", m.height);
                for (k, v) in [("fx", m.fx), ("fy", m.fy), ("cx", m.cx), ("cy", m.cy)] {
                    let _ = writeln!(out, "{k} = {v:?}");
                }
            }
        }
        out
    }
}

/// A TOML basic string: quotes, backslashes and control characters escaped.
fn toml_string(s: &str) -> String {
    let mut out = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() => {
                let _ = write!(out, "\\u{:04X}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::super::{file::parse, load, CameraModel, PixelConvention};

    #[test]
    fn to_toml_round_trips_every_shipped_camera_and_its_rescalings() {
        for name in ["f195.toml", "f165.toml", "pers.toml"] {
            let path = format!("{}/data/cameras/{name}", env!("CARGO_MANIFEST_DIR"));
            let cam = load(&path).unwrap();
            for s in [1.0, 0.1185, 0.237, 1.0 / 3.0] {
                let c = cam.rescaled([s, s], PixelConvention::HalfPixel);
                let text = c.to_toml(Some("F \"x\"\\y"), Some("rescaled\nby s"));
                let back = parse(&text, Path::new("written.toml")).unwrap();
                assert_eq!(back, c, "{name} x{s}:\n{text}");
            }
        }
    }
}
