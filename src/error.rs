//! The library's one error type. Every variant that comes from a file names the file, and where
//! it can, the field.

use std::path::PathBuf;

/// Errors of the calibconv library.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A TOML file did not parse (syntax error, unknown key, wrong type).
    #[error("{path}: {message}")]
    Toml { path: PathBuf, message: String },
    /// A file did not parse as the format it claims (a record, a data set file).
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    /// A camera file, a calibration import or a kernel's offsets failed (camera models and
    /// offsets live in the `calibconv-geometry` crate), or reading or writing any file failed
    /// (the geometry crate's `Io` variant, made by [`Error::io`]); its message unchanged.
    #[error(transparent)]
    Geometry(#[from] calibconv_geometry::Error),
    /// A function argument is outside what the operation supports.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A libtorch error.
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    /// An image could not be encoded or decoded.
    #[error("{path}: {message}")]
    Image { path: PathBuf, message: String },
    /// A data set file is missing, malformed or inconsistent (wrong size, unknown class index,
    /// manifest from another generator version...); `message` names the field where there is
    /// one.
    #[error("{path}: {message}")]
    Data {
        /// The offending file (or folder).
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// A checkpoint could not be read or written, or does not fit the network.
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: PathBuf, message: String },
    /// An experiment file parsed but a field is invalid (`field` is the dotted key path).
    #[error("{path}: `{field}`: {message}")]
    Config {
        path: PathBuf,
        field: String,
        message: String,
    },
    /// A record of a run directory (`summary.json`, `sweep.json`, ...) could not be read or
    /// written as its type (see [`crate::experiment::layout`]).
    #[error("{path}: {message}")]
    Record { path: PathBuf, message: String },
    /// A run directory is locked by another process (or another lock of this one).
    #[error(
        "{path} is in use by {holder} (it holds {path}/lock): wait for it to finish, or stop it"
    )]
    Busy { path: PathBuf, holder: String },
    /// Training produced a NaN or infinite value; nothing after `step` was saved.
    #[error(
        "training stopped: non-finite {what} ({value}) at step {step}; {}",
        match last_good {
            Some(p) => format!("the last good checkpoint is {}", p.display()),
            None => "no checkpoint was saved before it".to_string(),
        }
    )]
    NonFinite {
        step: u64,
        what: String,
        value: f64,
        last_good: Option<PathBuf>,
    },
    /// A run stopped on a signal (see [`crate::train::stop`]) after writing what it needs to
    /// continue; running it again resumes it. `what` says where it stopped.
    #[error(
        "stopped by {signal} {what}; resume it to continue (`calibconv train --resume`, or the \
         same sweep again)"
    )]
    Interrupted { signal: String, what: String },
    /// Writing a file failed (a full disk, an I/O error): `path` was not replaced, so the
    /// previous file, if there was one, is whole.
    #[error("cannot write {path}: {error} (the previous file, if any, is whole)")]
    Write {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// Result with the library's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A camera built in code with an invalid parameter (a model's `new`), through
/// [`Error::Geometry`].
impl From<calibconv_geometry::camera::Invalid> for Error {
    fn from(e: calibconv_geometry::camera::Invalid) -> Self {
        Error::Geometry(e.into())
    }
}

impl Error {
    /// Reading or writing `path` failed: the geometry crate's `Io` error (`{path}: {source}`,
    /// the I/O error as its source), through [`Error::Geometry`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Geometry(calibconv_geometry::Error::io(path, source))
    }

    /// Whether this is an [`Error::Interrupted`].
    pub fn is_interrupted(&self) -> bool {
        matches!(self, Error::Interrupted { .. })
    }

    /// An [`Error::Data`] for `path`.
    pub fn data(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Data {
            path: path.into(),
            message: message.into(),
        }
    }
}
