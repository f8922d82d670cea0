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
//! Section 3.1), [`Pinhole`], [`PinholeRadTan`] (OpenCV's 5- and 8-coefficient distortion),
//! [`DoubleSphere`], [`Unified`] and [`ExtendedUnified`] (Usenko et al. 2018), [`Mei`] (Mei's
//! unified model with radial-tangential distortion), [`Fov`] (Devernay and Faugeras),
//! [`Scaramuzza`] (OCamCalib) and [`Equirectangular`] (360-degree panoramas, the only model
//! whose kernels wrap horizontally). [`import`] reads the calibration files of other tools.
//!
//! A model's file also owns its camera-file schema: its `Raw` fields, its `validate()` (which its
//! `new` calls, so every camera in the program is checked) and its fields for [`to_toml`]. What
//! the models share is written once: [`Intrinsics`] (`fx fy cx cy width height`: checks, size,
//! rescaling), `schema` (the [`Invalid`] error, the checks, the header keys every file carries),
//! `solve` (the safeguarded 1-D Newton and the monotonic-range scan), `radtan` (the
//! radial-tangential distortion and its checked 2-D Newton inverse). `file` only reads
//! `model =` and hands the text to the model; the list of models is one table here
//! (`camera_models!`): a new model is its file plus its line in that table (see the crate docs).

mod file;
pub mod import;
mod intrinsics;
mod radtan;
mod schema;
mod solve;

pub use file::{parse, to_toml};
pub use intrinsics::Intrinsics;
pub use schema::Invalid;

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

/// A command-line enum's names: `NAMES`, the table of `(name, value)` in the order given, and
/// `FromStr` through it ([`from_name`]; `$what` names the enum in the error). Exported for the
/// enums of `calibconv` too.
#[macro_export]
macro_rules! from_str_by_name {
    ($ty:ident, $what:literal, { $($name:literal => $value:ident),* $(,)? }) => {
        impl $ty {
            /// Every value with its name on the command line and in files.
            const NAMES: [(&'static str, $ty); [$($name),*].len()] = [$(($name, $ty::$value)),*];
        }

        impl std::str::FromStr for $ty {
            type Err = String;
            fn from_str(s: &str) -> std::result::Result<Self, String> {
                $crate::camera::from_name($what, s, &<$ty>::NAMES)
            }
        }
    };
}
from_str_by_name!(PixelConvention, "pixel convention", {
    "half-pixel" => HalfPixel,
    "paper" => Paper,
});

/// The value named `s` in `names` (a command-line value's `FromStr`), or the error that lists
/// the names: ``unknown {what} `{s}` (expected a, b or c)``.
pub fn from_name<T: Copy>(
    what: &str,
    s: &str,
    names: &[(&str, T)],
) -> std::result::Result<T, String> {
    if let Some((_, value)) = names.iter().find(|(name, _)| *name == s) {
        return Ok(*value);
    }
    let list: Vec<&str> = names.iter().map(|(name, _)| *name).collect();
    let expected = match list.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{} or {last}", rest.join(", ")),
        _ => list.join(""),
    };
    Err(format!("unknown {what} `{s}` (expected {expected})"))
}

/// What every camera model offers.
pub trait CameraModel: Send + Sync + std::fmt::Debug {
    /// Pixel `[u, v]` of a ray `[x, y, z]` (any length > 0), or `None` outside the model's valid
    /// domain (behind a pinhole, past the monotonic range of a fisheye polynomial, zero ray).
    fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]>;
    /// [`CameraModel::project`] of many rays at once, given as columns `[x, y, z]` of equal
    /// length: ray `i` goes to `u[i], v[i]` with `ok[i] = true`, or gets `ok[i] = false` where
    /// `project` gives `None` (its `u[i], v[i]` are then unspecified). The same values as
    /// `project`, ray by ray; a model overrides it where a loop over whole columns is faster
    /// (Kannala-Brandt: vectorised). The calibrated offsets project a row of anchors per tap
    /// through it.
    fn project_columns(&self, rays: [&[f64]; 3], u: &mut [f64], v: &mut [f64], ok: &mut [bool]) {
        let [x, y, z] = rays;
        for (i, (ui, vi)) in u.iter_mut().zip(v.iter_mut()).enumerate() {
            let p = self.project([x[i], y[i], z[i]]);
            ok[i] = p.is_some();
            [*ui, *vi] = p.unwrap_or([0.0; 2]);
        }
    }
    /// Unit ray of pixel `[u, v]`, or `None` where the model has no inverse.
    fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]>;
    /// [`CameraModel::unproject`] of the pixels `[u, v]` given as columns: ray `i` goes to
    /// `rays[0..3][i]` with `ok[i] = true`, or gets `ok[i] = false` (its ray then unspecified).
    /// The same values as `unproject`, pixel by pixel; a model overrides it where whole columns
    /// are faster (Kannala-Brandt: Newton's iterations of four pixels in lockstep).
    fn unproject_columns(&self, px: [&[f64]; 2], rays: [&mut [f64]; 3], ok: &mut [bool]) {
        let [u, v] = px;
        let [x, y, z] = rays;
        for (i, ok) in ok.iter_mut().enumerate() {
            let ray = self.unproject([u[i], v[i]]);
            *ok = ray.is_some();
            [x[i], y[i], z[i]] = ray.unwrap_or([0.0; 3]);
        }
    }
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

/// Declares every camera model from one table of `Variant(module::Type)` lines: the model's
/// module and `pub use`, its [`Camera`] variant, its reader and `model =` name in [`MODELS`]
/// (the name is the model's `CameraFile::MODEL`, in its own file), and the dispatch of
/// [`CameraModel`], [`Camera::project_jacobian`], [`Camera::model_name`] and [`to_toml`]'s fields.
macro_rules! camera_models {
    ($($(#[$doc:meta])* $variant:ident($module:ident::$ty:ident),)*) => {
        $(mod $module; pub use $module::$ty;)*

        /// A camera of any supported model, as read from a camera file.
        #[derive(Clone, Debug, PartialEq)]
        pub enum Camera {
            $($(#[$doc])* $variant($ty),)*
        }

        /// The values of `model` that camera files may hold, in table order.
        pub const MODELS: [&str; [$(stringify!($variant)),*].len()] =
            [$(<$ty as schema::CameraFile>::MODEL),*];

        impl Camera {
            /// The camera of the model named `model` (one of [`MODELS`]) read from `text`, or
            /// `None` for an unknown model.
            fn read_model(model: &str, text: &str, path: &Path) -> Option<Result<Camera>> {
                $(if model == <$ty as schema::CameraFile>::MODEL {
                    return Some(file::read::<$ty>(text, path).map(Camera::$variant));
                })*
                None
            }
        }

        camera_models!(@dispatch [$($variant)*]);
    };
    // Every method of `Camera` that forwards to its model, written once over the variants.
    (@dispatch [$($variant:ident)*]) => {
        impl Camera {
            /// The model's name in camera files (`model = "..."`).
            pub fn model_name(&self) -> &'static str {
                fn name<M: schema::CameraFile>(_: &M) -> &'static str {
                    M::MODEL
                }
                match self { $(Camera::$variant(m) => name(m),)* }
            }

            /// Analytic Jacobian `d[u, v] / d[x, y, z]` of [`CameraModel::project`] (each model's
            /// `project_jacobian`), or `None` where `project` is `None` (and, for the
            /// equirectangular camera, at the poles).
            pub fn project_jacobian(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
                match self { $(Camera::$variant(m) => m.project_jacobian(ray),)* }
            }

            /// The model's checks (each model's `validate`, which its validating constructor
            /// runs); the error names the field.
            pub(crate) fn validate(&self) -> schema::Checked {
                match self { $(Camera::$variant(m) => m.validate(),)* }
            }

            /// `width`, `height`, then the model's fields, one `key = value` line each.
            fn write_fields(&self, out: &mut String) {
                use schema::CameraFile;
                match self { $(Camera::$variant(m) => m.write_fields(out),)* }
            }
        }

        impl CameraModel for Camera {
            fn project(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
                match self { $(Camera::$variant(m) => m.project(ray),)* }
            }
            fn unproject(&self, px: [f64; 2]) -> Option<[f64; 3]> {
                match self { $(Camera::$variant(m) => m.unproject(px),)* }
            }
            fn unproject_columns(
                &self,
                px: [&[f64]; 2],
                rays: [&mut [f64]; 3],
                ok: &mut [bool],
            ) {
                match self { $(Camera::$variant(m) => m.unproject_columns(px, rays, ok),)* }
            }
            fn project_columns(
                &self,
                rays: [&[f64]; 3],
                u: &mut [f64],
                v: &mut [f64],
                ok: &mut [bool],
            ) {
                match self { $(Camera::$variant(m) => m.project_columns(rays, u, v, ok),)* }
            }
            fn size(&self) -> [usize; 2] {
                match self { $(Camera::$variant(m) => m.size(),)* }
            }
            fn fov(&self) -> f64 {
                match self { $(Camera::$variant(m) => m.fov(),)* }
            }
            fn rescaled(&self, scale: [f64; 2], convention: PixelConvention) -> Camera {
                match self { $(Camera::$variant(m) => m.rescaled(scale, convention),)* }
            }
            fn wraps_horizontally(&self) -> bool {
                match self { $(Camera::$variant(m) => m.wraps_horizontally(),)* }
            }
            fn kernel_frame(&self) -> KernelFrame {
                match self { $(Camera::$variant(m) => m.kernel_frame(),)* }
            }
        }
    };
}

// The one list of models: a new model is its file plus its line here (see the crate docs).
camera_models! {
    /// `model = "kannala-brandt"` (the paper's model, Section 3.1).
    KannalaBrandt(kannala_brandt::KannalaBrandt),
    /// `model = "pinhole"`.
    Pinhole(pinhole::Pinhole),
    /// `model = "pinhole-radtan"`.
    PinholeRadTan(pinhole_radtan::PinholeRadTan),
    /// `model = "double-sphere"`.
    DoubleSphere(double_sphere::DoubleSphere),
    /// `model = "unified"`.
    Unified(unified::Unified),
    /// `model = "extended-unified"`.
    ExtendedUnified(extended_unified::ExtendedUnified),
    /// `model = "mei"` (Kalibr `omni-radtan`).
    Mei(mei::Mei),
    /// `model = "fov"` (Devernay and Faugeras).
    Fov(fov::Fov),
    /// `model = "scaramuzza"`.
    Scaramuzza(scaramuzza::Scaramuzza),
    /// `model = "equirectangular"`.
    Equirectangular(equirectangular::Equirectangular),
}

/// Reads a camera file (TOML, see `data/cameras/`) and returns its model.
pub fn load(path: impl AsRef<Path>) -> Result<Camera> {
    file::load(path.as_ref())
}

/// The largest angle to the optical axis a pixel's ray may make to be inside the image:
/// `fov_deg / 2` for the fisheye models (Kannala-Brandt, double sphere, unified, extended
/// unified, Mei, FOV, Scaramuzza: the image circle of the declared field of view); `None` (the image
/// rectangle is the only limit) for the perspective models and the equirectangular camera.
pub fn max_ray_angle(camera: &Camera) -> Option<f64> {
    let half = |fov_deg: f64| Some(fov_deg.to_radians() / 2.0);
    match camera {
        Camera::KannalaBrandt(m) => half(m.fov_deg),
        Camera::DoubleSphere(m) => half(m.fov_deg),
        Camera::Unified(m) => half(m.fov_deg),
        Camera::ExtendedUnified(m) => half(m.fov_deg),
        Camera::Scaramuzza(m) => half(m.fov_deg),
        Camera::Mei(m) => half(m.fov_deg),
        Camera::Fov(m) => half(m.fov_deg),
        Camera::Pinhole(_) | Camera::PinholeRadTan(_) | Camera::Equirectangular(_) => None,
    }
}

#[cfg(test)]
mod tests;
