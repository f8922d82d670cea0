//! The pinhole intrinsics shared by every model that has a focal length and a principal point
//! (Kannala-Brandt, pinhole, radial-tangential, double sphere, unified, extended unified): their
//! fields, checks, size and rescaling are written once here.

use super::schema::{check_finite, check_fov, check_size, Checked, Invalid};
use super::PixelConvention;
use crate::vec3::finite3;

/// Focal lengths, principal point and image size, in pixels (top-left pixel centre at 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along u, in pixels.
    pub fx: f64,
    /// Focal length along v, in pixels.
    pub fy: f64,
    /// Principal point column, in pixels (top-left pixel centre at 0).
    pub cx: f64,
    /// Principal point row, in pixels (top-left pixel centre at 0).
    pub cy: f64,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
}

impl Intrinsics {
    /// From `[fx, fy, cx, cy]` and `[width, height]` (a camera file's fields).
    pub fn from_parts([fx, fy, cx, cy]: [f64; 4], [width, height]: [usize; 2]) -> Self {
        Intrinsics {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// The float fields as named in camera files, in file order (`fx fy cx cy`).
    pub fn fields(&self) -> [(&'static str, f64); 4] {
        [
            ("fx", self.fx),
            ("fy", self.fy),
            ("cx", self.cx),
            ("cy", self.cy),
        ]
    }

    /// `fx, fy > 0` and `width, height > 0` (finiteness is checked with the model's other
    /// fields, in file order, by the model's `validate`).
    pub fn validate(&self) -> Checked {
        for (field, f) in [("fx", self.fx), ("fy", self.fy)] {
            if f <= 0.0 {
                return Err(Invalid::new(
                    field,
                    format!("focal length must be > 0 px, found {f}"),
                ));
            }
        }
        check_size(self.width, self.height)
    }

    /// A fisheye model's float fields in file order: `fov_deg`, `fx fy cx cy`, then `params`.
    pub(crate) fn with_fov(
        &self,
        fov_deg: f64,
        params: &[(&'static str, f64)],
    ) -> Vec<(&'static str, f64)> {
        let mut fields = vec![("fov_deg", fov_deg)];
        fields.extend(self.fields());
        fields.extend_from_slice(params);
        fields
    }

    /// The checks every fisheye model starts with: its `fields` finite (in file order), then
    /// [`Intrinsics::validate`], then `0 < fov_deg < 360`.
    pub(crate) fn validate_fisheye(&self, fields: &[(&str, f64)], fov_deg: f64) -> Checked {
        check_finite(fields.iter().copied())?;
        self.validate()?;
        check_fov(fov_deg)
    }

    /// Image size `[width, height]` in pixels.
    pub fn size(&self) -> [usize; 2] {
        [self.width, self.height]
    }

    /// `fx sx`, `fy sy`, the principal point moved by `convention`, size `round(width sx)` x
    /// `round(height sy)` (Section 3.2 of the paper).
    pub fn rescaled(&self, [sx, sy]: [f64; 2], convention: PixelConvention) -> Self {
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: convention.scale_centre(self.cx, sx),
            cy: convention.scale_centre(self.cy, sy),
            width: (self.width as f64 * sx).round() as usize,
            height: (self.height as f64 * sy).round() as usize,
        }
    }
}

impl Intrinsics {
    /// `[fx x / den + cx, fy y / den + cy]`: the pixel of the ray `[x, y, z]` for a model that
    /// divides by a denominator `den` (the unified family: Usenko et al. 2018 Eqs. 14, 22, 40).
    pub(crate) fn project_divided(&self, ray: [f64; 3], den: f64) -> [f64; 2] {
        [
            self.fx * ray[0] / den + self.cx,
            self.fy * ray[1] / den + self.cy,
        ]
    }

    /// The Jacobian `d[u, v] / d[x, y, z]` of [`Intrinsics::project_divided`] given the gradient
    /// `dden` of the denominator: `du/dp = fx (e_x / den - x dden / den^2)`,
    /// `dv/dp = fy (e_y / den - y dden / den^2)`.
    pub(crate) fn divided_jacobian(
        &self,
        ray: [f64; 3],
        den: f64,
        dden: [f64; 3],
    ) -> [[f64; 3]; 2] {
        let row = |f: f64, c: f64, axis: usize| {
            [0, 1, 2].map(|i| {
                let e = if i == axis { 1.0 } else { 0.0 };
                f * (e / den - c * dden[i] / (den * den))
            })
        };
        [row(self.fx, ray[0], 0), row(self.fy, ray[1], 1)]
    }
}

/// A model whose projection divides by a denominator of the ray (the unified family: Usenko et
/// al. 2018 Eqs. 14, 22, 40): `u = fx x / den + cx`, `v = fy y / den + cy`. The model gives its
/// denominator and the denominator's gradient; its `project` ([`Divided::project_by_den`]) and
/// `project_jacobian` ([`Divided::jacobian_by_den`], the quotient rule of
/// [`Intrinsics::divided_jacobian`]) are written once here.
pub(crate) trait Divided: std::ops::Deref<Target = Intrinsics> {
    /// What the denominator is computed from and its gradient needs (the ray's norms).
    type Parts;
    /// `(den, parts)` of a finite ray inside the model's domain, or `None` outside it.
    fn den(&self, ray: [f64; 3]) -> Option<(f64, Self::Parts)>;
    /// The gradient `d den / d[x, y, z]` at a ray inside the domain.
    fn den_gradient(&self, ray: [f64; 3], parts: Self::Parts) -> [f64; 3];

    /// [`Intrinsics::project_divided`], or `None` for a non-finite ray or one outside the domain.
    fn project_by_den(&self, ray: [f64; 3]) -> Option<[f64; 2]> {
        if !finite3(ray) {
            return None;
        }
        let (den, _) = self.den(ray)?;
        Some(self.project_divided(ray, den))
    }

    /// [`Intrinsics::divided_jacobian`] with [`Divided::den_gradient`], or `None` where
    /// [`Divided::project_by_den`] is `None`.
    fn jacobian_by_den(&self, ray: [f64; 3]) -> Option<[[f64; 3]; 2]> {
        if !finite3(ray) {
            return None;
        }
        let (den, parts) = self.den(ray)?;
        Some(self.divided_jacobian(ray, den, self.den_gradient(ray, parts)))
    }
}

/// The [`super::CameraModel`] methods every fisheye model with fields `intrinsics` and
/// `fov_deg` (and nothing derived from the intrinsics) writes alike: `size`, `fov` (`fov_deg` in
/// radians) and `rescaled` (the intrinsics rescaled, the model's parameters unchanged: they are
/// angular). Expands inside the model's `impl CameraModel`; `$variant` is its [`super::Camera`]
/// variant.
macro_rules! fisheye_extent {
    ($variant:ident) => {
        fn size(&self) -> [usize; 2] {
            self.intrinsics.size()
        }

        /// `fov_deg` in radians.
        fn fov(&self) -> f64 {
            self.fov_deg.to_radians()
        }

        /// The intrinsics rescaled ([`Intrinsics::rescaled`]); the model's parameters and
        /// `fov_deg` unchanged.
        fn rescaled(
            &self,
            scale: [f64; 2],
            convention: $crate::camera::PixelConvention,
        ) -> $crate::camera::Camera {
            $crate::camera::Camera::$variant(Self {
                intrinsics: self.intrinsics.rescaled(scale, convention),
                ..self.clone()
            })
        }
    };
}
pub(crate) use fisheye_extent;

/// Lets a model read its intrinsics as its own fields (`cam.fx`); they are set only through
/// the model's validating constructor.
macro_rules! deref_intrinsics {
    ($model:ty) => {
        impl std::ops::Deref for $model {
            type Target = $crate::camera::Intrinsics;
            fn deref(&self) -> &$crate::camera::Intrinsics {
                &self.intrinsics
            }
        }
    };
}
pub(crate) use deref_intrinsics;

/// `PartialEq` of a model that compares the named fields only: the fields it leaves out are
/// derived from them by the model's constructor (a monotonic range, a distortion's domain), so
/// equal parameters make equal cameras.
macro_rules! eq_by_fields {
    ($model:ty: $first:ident $(, $field:ident)* $(,)?) => {
        impl PartialEq for $model {
            fn eq(&self, other: &Self) -> bool {
                self.$first == other.$first $(&& self.$field == other.$field)*
            }
        }
    };
}
pub(crate) use eq_by_fields;
