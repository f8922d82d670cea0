//! Camera models in plain `f64` Rust (no tensors).
//!
//! Conventions used by every model in this module:
//! - pixel coordinates are `[u, v]` = (column, row), in pixels, with the centre of the top-left
//!   pixel at `(0, 0)` (the OpenCV convention);
//! - rays are `[x, y, z]` in the camera frame: x right, y down, z forward (optical axis);
//!   [`CameraModel::unproject`] returns unit rays; [`CameraModel::project`] accepts any non-zero
//!   ray;
//! - angles are radians everywhere except in camera files (`fov_deg`).
//!
//! Models, one file each, each documenting its formula and source: [`KannalaBrandt`] (paper
//! Section 3.1), [`Pinhole`], [`PinholeRadTan`] (OpenCV's 5-parameter distortion),
//! [`DoubleSphere`], [`Unified`] and [`ExtendedUnified`] (Usenko et al. 2018), [`Scaramuzza`]
//! (OCamCalib) and [`Equirectangular`] (360-degree panoramas, the only model whose kernels wrap
//! horizontally). [`import`] reads the calibration files of other tools.
//!
//! A model's file also owns its camera-file schema: its `Raw` fields, its `validate()` (which its
//! `new` calls, so every camera in the program is checked) and its fields for [`to_toml`]. What
//! the models share is written once: [`Intrinsics`] (`fx fy cx cy width height`: checks, size,
//! rescaling), `schema` (the [`Invalid`] error, the checks, the header keys every file carries),
//! `solve` (the safeguarded 1-D Newton and the monotonic-range scan). `file` only dispatches on
//! `model =`. A new model is its file, plus here its `mod` / `pub use`, its [`Camera`] variant and
//! its `dispatch!` arm, and its line in `file`'s reader table.

mod double_sphere;
mod equirectangular;
mod extended_unified;
mod geometry;
pub mod import;
mod intrinsics;
mod kannala_brandt;
mod pinhole;
mod pinhole_radtan;
mod scaramuzza;
mod schema;
mod solve;
mod unified;

pub use double_sphere::DoubleSphere;
pub use equirectangular::Equirectangular;
pub use extended_unified::ExtendedUnified;
pub use intrinsics::Intrinsics;
pub use kannala_brandt::KannalaBrandt;
pub use pinhole::Pinhole;
pub use pinhole_radtan::PinholeRadTan;
pub use scaramuzza::Scaramuzza;
pub use schema::Invalid;
pub use unified::Unified;

use std::path::Path;

use crate::error::Result;

/// How intrinsics move to another resolution (Section 3.2 of the paper, "scaling factor").
///
/// With scale `s` = new size / old size:
/// - `HalfPixel` (default): `c' = (c + 0.5) s - 0.5`, exact for average-pooled / resized maps
///   whose pixel centres sit at half-integers of the original grid;
/// - `Paper`: `c' = c s`, exactly the authors' released code (off by `(s - 1) / 2` pixels).
///
/// Focal lengths scale as `f' = f s` in both.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum PixelConvention {
    #[default]
    HalfPixel,
    Paper,
}

impl PixelConvention {
    /// Moves a principal-point coordinate `c` to a grid scaled by `s`.
    pub fn scale_centre(self, c: f64, s: f64) -> f64 {
        match self {
            PixelConvention::HalfPixel => (c + 0.5) * s - 0.5,
            PixelConvention::Paper => c * s,
        }
    }
}

impl std::str::FromStr for PixelConvention {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "half-pixel" => Ok(PixelConvention::HalfPixel),
            "paper" => Ok(PixelConvention::Paper),
            other => Err(format!(
                "unknown pixel convention `{other}` (expected half-pixel or paper)"
            )),
        }
    }
}

/// What every camera model offers.
pub trait CameraModel: Send + Sync + std::fmt::Debug {
    /// Pixel `[u, v]` of a ray `[x, y, z]` (any length > 0), or `None` outside the model's valid
    /// domain (behind a pinhole, past the monotonic range of a fisheye polynomial, zero ray).
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]>;
    /// Unit ray of pixel `[u, v]`, or `None` where the model has no inverse.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]>;
    /// Image size `[width, height]` in pixels.
    fn size(&self) -> [usize; 2];
    /// Full horizontal field of view in radians.
    fn fov(&self) -> f64;
    /// The same camera seen at another resolution: intrinsics scaled by `[sx, sy]` (new / old),
    /// the principal point moved by `convention`, the image size rounded.
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera;
    /// Whether the image is periodic horizontally (a 360-degree panorama): kernels then continue
    /// across the left/right edge, offsets are taken modulo the feature-map width and the
    /// sampling plan wraps columns instead of reading zeros.
    fn wraps_horizontally(&self) -> bool {
        false
    }
    /// How calibrated kernels are oriented on the sphere (see [`KernelFrame`]).
    fn kernel_frame(&self) -> KernelFrame {
        KernelFrame::MinimalRotation
    }
}

/// The orientation of a calibrated kernel's virtual perspective patch around its anchor ray.
///
/// Any smooth choice of orientation over the whole sphere has a singular point (the hairy-ball
/// theorem); each choice puts it somewhere else.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum KernelFrame {
    /// The paper's choice (Section 3.2): the minimal rotation taking the optical axis onto the
    /// anchor ray. Singular only at the backward ray `-z`, outside any fisheye's view.
    #[default]
    MinimalRotation,
    /// Yaw then pitch, no roll: the patch's rows stay horizontal (its x axis along increasing
    /// longitude, its y axis towards the south pole), as in the tangent-plane kernels of Tateno et
    /// al. and EquiConvs. Singular only at the poles. Used by panoramas, where the minimal
    /// rotation's singular point (straight back) lies on the seam and turns the kernels around it
    /// by up to 180 degrees between neighbouring pixels.
    Upright,
}

/// A camera of any supported model, as read from a camera file.
#[derive(Clone, Debug, PartialEq)]
pub enum Camera {
    /// `model = "kannala-brandt"`.
    KannalaBrandt(KannalaBrandt),
    /// `model = "pinhole"`.
    Pinhole(Pinhole),
    /// `model = "pinhole-radtan"`.
    PinholeRadTan(PinholeRadTan),
    /// `model = "double-sphere"`.
    DoubleSphere(DoubleSphere),
    /// `model = "unified"`.
    Unified(Unified),
    /// `model = "extended-unified"`.
    ExtendedUnified(ExtendedUnified),
    /// `model = "scaramuzza"`.
    Scaramuzza(Scaramuzza),
    /// `model = "equirectangular"`.
    Equirectangular(Equirectangular),
}

macro_rules! dispatch {
    ($self:ident, $m:ident => $e:expr) => {
        match $self {
            Camera::KannalaBrandt($m) => $e,
            Camera::Pinhole($m) => $e,
            Camera::PinholeRadTan($m) => $e,
            Camera::DoubleSphere($m) => $e,
            Camera::Unified($m) => $e,
            Camera::ExtendedUnified($m) => $e,
            Camera::Scaramuzza($m) => $e,
            Camera::Equirectangular($m) => $e,
        }
    };
}

impl Camera {
    /// The model's name in camera files (`model = "..."`).
    pub fn model_name(&self) -> &'static str {
        fn name<M: schema::CameraFile>(_: &M) -> &'static str {
            M::MODEL
        }
        dispatch!(self, m => name(m))
    }

    /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`] (each model's
    /// `project_jacobian`), or `None` where `project` is `None` (and, for the equirectangular
    /// camera, at the poles).
    pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        dispatch!(self, m => m.project_jacobian(ray))
    }
}

impl CameraModel for Camera {
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        dispatch!(self, m => m.project(ray))
    }
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
        dispatch!(self, m => m.unproject(px))
    }
    fn size(&self) -> [usize; 2] {
        dispatch!(self, m => m.size())
    }
    fn fov(&self) -> f64 {
        dispatch!(self, m => m.fov())
    }
    fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
        dispatch!(self, m => m.rescaled(scale, convention))
    }
    fn wraps_horizontally(&self) -> bool {
        dispatch!(self, m => m.wraps_horizontally())
    }
    fn kernel_frame(&self) -> KernelFrame {
        dispatch!(self, m => m.kernel_frame())
    }
}

/// Reads a camera file (TOML, see `data/cameras/`) and returns its model.
pub fn load(path: impl AsRef<Path>) -> Result<Camera> {
    file::load(path.as_ref())
}

mod file;

pub use file::{parse, to_toml, MODELS};

#[cfg(test)]
mod tests;
