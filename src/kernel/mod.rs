//! The paper's "fisheye calibrated kernel" (Section 3.2): the offsets themselves are computed
//! as plain data by [`calibconv_geometry::kernel`] (re-exported here, so `calibconv::kernel::X`
//! names the same items); this module adds what needs tensors: [`OffsetsTensor::to_tensor`] and
//! the process-wide offsets cache ([`cached_offsets`]). [`compute_offsets`] and [`kernel_focal`]
//! return the geometry crate's error, which `?` turns into the library's
//! [`Error::Geometry`](crate::Error::Geometry) (same messages).

mod cache;

pub use cache::{cached_offsets, clear_offsets_cache};
pub use calibconv_geometry::kernel::*;

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
