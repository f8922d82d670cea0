//! [`CamMapsConv2d`]: CAM-Convs (Facil et al., CVPR 2019) extended to any camera model.
//!
//! CAM-Convs concatenate camera maps to the feature maps where the decoder reads the encoder's
//! skip connections, so that the convolution after each skip can condition on the pixel's place
//! in the field of view. The maps here are the pixel's unit ray and a validity mask
//! ([`crate::kernel::ray_maps`]: defined and continuous on every model's whole domain, where the
//! pinhole maps of the original are not).
//!
//! Concatenating `M` constant maps to the input of a convolution `W` equals adding the
//! convolution of the maps alone with the new `M` input channels of `W`:
//! `conv([x; maps], [W_x, W_m]) = conv(x, W_x) + conv(maps, W_m)`. The layer computes it that way:
//! the convolution keeps its shape and names (`weight`, `bias`: a checkpoint of the plain U-Net
//! loads unchanged) and the map weight `W_m` `[C_out, 4, k, k]` is a parameter of its own under
//! `added.cam_maps.weight`, zero-initialised, so that at the first step the network computes
//! exactly the function of the checkpoint it starts from.

use tch::nn::{self, Module};
use tch::Tensor;

use super::{CameraInput, Conv2dConfig};
use crate::error::Result;
use crate::kernel::{ray_maps, RAY_MAPS};

/// A standard `k x k` convolution plus the CAM-Conv camera-map term.
#[derive(Debug)]
pub struct CamMapsConv2d {
    pub conv: nn::Conv2D,
    /// `[1, RAY_MAPS, H, W]` on the layer's device (constant).
    maps: Tensor,
    /// `[C_out, RAY_MAPS, k, k]`, zero at construction.
    pub maps_weight: Tensor,
    cfg: Conv2dConfig,
    k: i64,
}

impl CamMapsConv2d {
    /// Creates the layer under `vs` for the input feature map `input`.
    pub fn new(
        vs: &nn::Path,
        c_in: i64,
        c_out: i64,
        k: i64,
        input: CameraInput<'_>,
        cfg: Conv2dConfig,
    ) -> Result<Self> {
        let conv = nn::conv(vs, c_in, c_out, [k, k], cfg.to_tch(k));
        let [h, w] = input.size;
        let m = ray_maps(
            input.camera,
            input.size.map(|v| v.max(0) as usize),
            input.frame,
        )?;
        let maps = Tensor::from_slice(&m.data)
            .view([1, RAY_MAPS as i64, h, w])
            .to_device(vs.device());
        let maps_weight = (vs / super::ADDED / "cam_maps").var(
            "weight",
            &[c_out, RAY_MAPS as i64, k, k],
            nn::Init::Const(0.0),
        );
        Ok(CamMapsConv2d {
            conv,
            maps,
            maps_weight,
            cfg,
            k,
        })
    }
}

impl Module for CamMapsConv2d {
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]` with `[H, W]` the size the layer was built for
    /// - output: `[B, C_out, H_out, W_out]`
    fn forward(&self, xs: &Tensor) -> Tensor {
        let s = xs.size();
        let m = self.maps.size();
        assert!(
            s.len() == 4 && s[2..] == m[2..],
            "CamMapsConv2d: camera maps were built for {}x{}, got input {s:?}",
            m[2],
            m[3]
        );
        let t = self.cfg.to_tch(self.k);
        let maps = self.maps.to_kind(xs.kind());
        let term = maps.conv2d(
            &self.maps_weight,
            None::<&Tensor>,
            t.stride,
            t.padding,
            t.dilation,
            1,
        );
        self.conv.forward(xs) + term
    }
}
