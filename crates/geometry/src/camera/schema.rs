//! What every camera model's file schema shares: the [`Invalid`] error of a model's checks, the
//! checks themselves, the header keys every camera file may carry, and the float writer.
//!
//! A model owns its schema: its `Raw` struct (declared with [`raw_camera_file!`], so the header
//! keys are written once), its `validate()` and its fields for [`super::to_toml`], through
//! [`CameraFile`]. `super::file` only dispatches on `model =`.

use std::path::Path;

use super::CameraModel;
use crate::error::Error;

/// A camera parameter outside what its model accepts: the field (as named in camera files) and
/// why. [`Invalid::in_file`] names the file too.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("camera field `{field}`: {message}")]
pub struct Invalid {
    /// The field, as named in camera files (`fx`, `k1..k4`, `c, d, e`).
    pub field: String,
    /// What is wrong with it.
    pub message: String,
}

impl Invalid {
    pub(crate) fn new(field: &str, message: String) -> Self {
        Invalid {
            field: field.to_string(),
            message,
        }
    }

    /// The same error, naming the file it was read from.
    pub fn in_file(self, path: &Path) -> Error {
        Error::Camera {
            path: path.to_path_buf(),
            field: self.field,
            message: self.message,
        }
    }
}

/// The checks' result.
pub type Checked = std::result::Result<(), Invalid>;

/// A camera model as a camera file: its `model =` name, its `Raw` fields and how they become a
/// checked camera, and the named float fields it writes (in file order).
pub(crate) trait CameraFile: CameraModel + Sized {
    /// The value of `model` in camera files.
    const MODEL: &'static str;
    /// The file as written (serde, `deny_unknown_fields`).
    type Raw: serde::de::DeserializeOwned;
    /// The checked camera of a file (the model's validating constructor).
    fn from_raw(raw: Self::Raw) -> Result<Self, Invalid>;
    /// The float fields as named in camera files, in file order (lists such as a polynomial
    /// aside): what the model's `validate` checks for finiteness and [`super::to_toml`] writes.
    fn fields(&self) -> Vec<(&'static str, f64)>;
    /// `width`, `height`, then the model's fields, one `key = value` line each, in file order.
    fn write_fields(&self, out: &mut String) {
        write_fields(out, self.size(), &self.fields());
    }
}

/// `cam` if `validate` accepts it: the body of every model's `new`.
pub(crate) fn checked<T>(cam: T, validate: fn(&T) -> Checked) -> Result<T, Invalid> {
    validate(&cam)?;
    Ok(cam)
}

/// Declares a camera file's `Raw` struct: the model's own fields plus the header keys every file
/// may carry (`model`, read by the dispatch in `super::file`; `name` and `description`,
/// documentation only), with `deny_unknown_fields` so that a misspelt key is an error naming it.
/// `pinhole struct` starts with `width height fx fy cx cy`, `fisheye struct` with
/// `width height fov_deg fx fy cx cy`; both give the struct an `intrinsics()` method.
macro_rules! raw_camera_file {
    ($(#[$meta:meta])* fisheye struct $name:ident { $($body:tt)* }) => {
        $crate::camera::schema::raw_camera_file! {
            @intrinsics $(#[$meta])* struct $name {
                width: usize, height: usize, fov_deg: f64, fx: f64, fy: f64, cx: f64, cy: f64,
                $($body)*
            }
        }
    };
    ($(#[$meta:meta])* pinhole struct $name:ident { $($body:tt)* }) => {
        $crate::camera::schema::raw_camera_file! {
            @intrinsics $(#[$meta])* struct $name {
                width: usize, height: usize, fx: f64, fy: f64, cx: f64, cy: f64,
                $($body)*
            }
        }
    };
    (@intrinsics $(#[$meta:meta])* struct $name:ident { $($body:tt)* }) => {
        $crate::camera::schema::raw_camera_file! { $(#[$meta])* struct $name { $($body)* } }
        impl $name {
            /// The file's `fx fy cx cy width height`.
            fn intrinsics(&self) -> $crate::camera::Intrinsics {
                let f = [self.fx, self.fy, self.cx, self.cy];
                $crate::camera::Intrinsics::from_parts(f, [self.width, self.height])
            }
        }
    };
    ($(#[$meta:meta])* struct $name:ident {
        $($(#[$fmeta:meta])* $field:ident : $ty:ty),* $(,)?
    }) => {
        $(#[$meta])*
        #[derive(serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        pub(crate) struct $name {
            #[serde(rename = "model")]
            _model: String,
            #[serde(rename = "name")]
            _name: Option<String>,
            #[serde(rename = "description")]
            _description: Option<String>,
            $($(#[$fmeta])* $field: $ty,)*
        }
    };
}
pub(crate) use raw_camera_file;

/// The schema and constructors of a fisheye model whose fields are `intrinsics`, its float
/// parameters `$param` (in file order) and `fov_deg`, with nothing derived (double sphere,
/// unified, extended unified): its `Raw` ([`raw_camera_file!`], `fisheye struct`), its
/// [`CameraFile`] (`model = $name`) and `new` / `unchecked` taking `(intrinsics, $param..,
/// fov_deg)`, its intrinsics read as its own fields ([`deref_intrinsics!`]), and `validate`,
/// which `new` calls: the intrinsics and `fov_deg` ([`Intrinsics::validate_fisheye`]), then the
/// model's own `check_parameters(&self) -> Checked` (the parameters' ranges), then `fov_deg / 2`
/// inside the model's `theta_max(&self)`.
///
/// [`Intrinsics::validate_fisheye`]: super::Intrinsics::validate_fisheye
///
/// [`deref_intrinsics!`]: super::intrinsics::deref_intrinsics
macro_rules! plain_fisheye_file {
    ($model:ident, $name:literal, [$($param:ident),+]) => {
        $crate::camera::intrinsics::deref_intrinsics!($model);

        $crate::camera::schema::raw_camera_file! {
            #[doc = concat!("A `", $name, "` camera file as written.")]
            fisheye struct Raw {
                $($param: f64,)+
            }
        }

        impl $crate::camera::schema::CameraFile for $model {
            const MODEL: &'static str = $name;
            type Raw = Raw;
            fn fields(&self) -> Vec<(&'static str, f64)> {
                let params = [$((stringify!($param), self.$param)),+];
                self.intrinsics.with_fov(self.fov_deg, &params)
            }
            fn from_raw(r: Raw) -> Result<Self, $crate::camera::Invalid> {
                $model::new(r.intrinsics(), $(r.$param,)+ r.fov_deg)
            }
        }

        impl $model {
            #[doc = concat!(
                "Every float finite, the intrinsics ([`Intrinsics::validate`]), `0 < fov_deg < ",
                "360`, the parameters ",
                $("`", stringify!($param), "` ",)+
                "in their ranges (see the model's docs), and `fov_deg / 2` below [`",
                stringify!($model),
                "::theta_max`]; the error names the field.\n\n",
                "[`Intrinsics::validate`]: crate::camera::Intrinsics::validate"
            )]
            pub fn validate(&self) -> $crate::camera::schema::Checked {
                self.intrinsics.validate_fisheye(&self.fields(), self.fov_deg)?;
                self.check_parameters()?;
                let params = [$(stringify!($param)),+].join(", ");
                $crate::camera::schema::check_fov_in_domain(self.fov_deg, self.theta_max(), &params)
            }

            #[doc = concat!("A checked camera (see [`", stringify!($model), "::validate`]).")]
            pub fn new(
                intrinsics: $crate::camera::Intrinsics,
                $($param: f64,)+
                fov_deg: f64,
            ) -> Result<Self, $crate::camera::Invalid> {
                let cam = Self::unchecked(intrinsics, $($param,)+ fov_deg);
                $crate::camera::schema::checked(cam, Self::validate)
            }

            /// The camera without the checks: for probing the model's domain before its field
            /// of view is known.
            pub(crate) fn unchecked(
                intrinsics: $crate::camera::Intrinsics,
                $($param: f64,)+
                fov_deg: f64,
            ) -> Self {
                $model {
                    intrinsics,
                    $($param,)+
                    fov_deg,
                }
            }
        }
    };
}
pub(crate) use plain_fisheye_file;

/// A parameter's range check: `Ok` where `holds`, else the error naming `field`: "must be
/// `{rule}`, found `{v}`" (`rule` as the model's docs state it: `in (-1, 1]`, `> 0`).
pub(crate) fn check_rule(field: &str, v: f64, holds: bool, rule: &str) -> Checked {
    if holds {
        Ok(())
    } else {
        Err(Invalid::new(field, format!("must be {rule}, found {v}")))
    }
}

/// The first non-finite field, if any.
pub(crate) fn check_finite<'a>(fields: impl IntoIterator<Item = (&'a str, f64)>) -> Checked {
    fields
        .into_iter()
        .try_for_each(|(field, v)| check_rule(field, v, v.is_finite(), "finite"))
}

/// `width, height > 0`.
pub(crate) fn check_size(width: usize, height: usize) -> Checked {
    for (field, n) in [("width", width), ("height", height)] {
        if n == 0 {
            return Err(Invalid::new(field, "must be > 0 px".to_string()));
        }
    }
    Ok(())
}

/// `0 < fov_deg < 360`.
pub(crate) fn check_fov(fov_deg: f64) -> Checked {
    let holds = fov_deg > 0.0 && fov_deg < 360.0;
    check_rule("fov_deg", fov_deg, holds, "in (0, 360) degrees")
}

/// `v in [0, 1]`.
pub(crate) fn check_unit_interval(field: &str, v: f64) -> Checked {
    check_rule(field, v, (0.0..=1.0).contains(&v), "in [0, 1]")
}

/// `fov_deg / 2` must be below the model's largest projectable angle `theta_max` (radians),
/// which `params` (the fields that set it) determine.
pub(crate) fn check_fov_in_domain(fov_deg: f64, theta_max: f64, params: &str) -> Checked {
    if (fov_deg / 2.0).to_radians() < theta_max {
        Ok(())
    } else {
        Err(Invalid::new(
            "fov_deg",
            format!(
                "fov_deg/2 = {:.3} deg, but with these {params} the model projects rays only up \
                 to {:.3} deg from the optical axis",
                fov_deg / 2.0,
                theta_max.to_degrees()
            ),
        ))
    }
}

/// Writes `width`, `height` and then `key = value` for each float, shortest round-trip text.
pub(crate) fn write_fields(out: &mut String, [width, height]: [usize; 2], floats: &[(&str, f64)]) {
    out.push_str(&format!("width = {width}\nheight = {height}\n"));
    for (key, value) in floats {
        out.push_str(&format!("{key} = {}\n", float(*value)));
    }
}

/// `{:?}` prints the shortest text that reads back to the same `f64` (`1.0`, `1e-5`, `-0.25`),
/// always a valid TOML float for finite values.
pub(crate) fn float(v: f64) -> String {
    format!("{v:?}")
}

/// `[a, b, ...]` of [`float`]s.
pub(crate) fn float_list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|v| float(*v)).collect();
    format!("[{}]", items.join(", "))
}
