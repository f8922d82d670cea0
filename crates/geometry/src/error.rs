//! The geometry crate's one error type: what reading a camera, importing a calibration and
//! computing offsets can fail with. Every variant that comes from a file names the file, and
//! where it can, the field. `calibconv::Error` wraps it unchanged (same messages), and makes
//! its own I/O errors as [`Error::Io`] too (`calibconv::Error::io`).

use std::path::PathBuf;

/// Errors of camera models, camera files, calibration import and kernel offsets.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A TOML file did not parse (syntax error, unknown key, wrong type).
    #[error("{path}: {message}")]
    Toml { path: PathBuf, message: String },
    /// A camera file parsed but one of its fields is invalid.
    #[error("{path}: field `{field}`: {message}")]
    Camera {
        path: PathBuf,
        field: String,
        message: String,
    },
    /// A calibration file of another tool (Kalibr, OpenCV, Basalt, COLMAP, OCamCalib, ROS,
    /// ORB-SLAM3) did not parse as that tool writes it.
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    /// A camera built in code (not read from a file) has an invalid parameter.
    #[error(transparent)]
    InvalidCamera(#[from] crate::camera::Invalid),
    /// A function argument is outside what the operation supports.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

/// Result with the geometry crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An [`Error::Io`] for `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}
