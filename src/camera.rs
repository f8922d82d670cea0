//! Camera models, camera files and calibration import: the [`calibconv_geometry::camera`]
//! module of the tensor-free geometry crate (`crates/geometry`), re-exported so that
//! `calibconv::camera::X` names the same items. [`load`] and [`parse`] return the library's
//! [`Error`](crate::Error) (wrapping the geometry crate's, same messages).

use std::path::Path;

pub use calibconv_geometry::camera::*;

use crate::error::Result;

/// Reads a camera file (TOML, see `data/cameras/`) and returns its model
/// ([`calibconv_geometry::camera::load`]).
pub fn load(path: impl AsRef<Path>) -> Result<Camera> {
    Ok(calibconv_geometry::camera::load(path)?)
}

/// Parses the text of a camera file; `path` only names the file in errors
/// ([`calibconv_geometry::camera::parse`]).
pub fn parse(text: &str, path: &Path) -> Result<Camera> {
    Ok(calibconv_geometry::camera::parse(text, path)?)
}

/// A camera file shipped in `data/cameras/` (`NAME.toml`), for the unit tests.
///
/// # Panics
/// If the file is missing or invalid.
#[cfg(test)]
pub(crate) fn shipped(name: &str) -> Camera {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("data/cameras/{name}.toml"));
    load(&path).unwrap_or_else(|e| panic!("{e}"))
}
