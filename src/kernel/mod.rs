//! The paper's "fisheye calibrated kernel" (Section 3.2): the offsets themselves are computed
//! as plain data by [`calibconv_geometry::kernel`] (re-exported here, so `calibconv::kernel::X`
//! names the same items); this module adds what needs tensors: [`OffsetsTensor::to_tensor`] and
//! the process-wide offsets cache ([`cached_offsets`]). [`compute_offsets`] and [`kernel_focal`]
//! return the library's [`Error`](crate::Error) (wrapping the geometry crate's, same messages).

mod cache;

pub use cache::{cached_offsets, clear_offsets_cache};
pub use calibconv_geometry::kernel::*;

use crate::camera::Camera;
use crate::error::Result;

/// Computes the calibrated offsets of one layer ([`calibconv_geometry::kernel::compute_offsets`],
/// whose docs give the conventions and errors).
pub fn compute_offsets(
    camera: &Camera,
    input_size: [usize; 2],
    geometry: &LayerGeometry,
    frame: &InputFrame,
) -> Result<Offsets> {
    Ok(calibconv_geometry::kernel::compute_offsets(
        camera, input_size, geometry, frame,
    )?)
}

/// The focal length of a layer's virtual perspective kernel
/// ([`calibconv_geometry::kernel::kernel_focal`]).
pub fn kernel_focal(k: usize, fov: f64, w_fm: usize) -> Result<f64> {
    Ok(calibconv_geometry::kernel::kernel_focal(k, fov, w_fm)?)
}

/// [`Offsets`] as a tensor.
pub trait OffsetsTensor {
    /// The offsets as a `[2*kh*kw, H_out, W_out]` float32 CPU tensor.
    fn to_tensor(&self) -> tch::Tensor;
}

impl OffsetsTensor for Offsets {
    fn to_tensor(&self) -> tch::Tensor {
        let shape = self.shape().map(|n| n as i64);
        tch::Tensor::from_slice(&self.data).view(shape)
    }
}
