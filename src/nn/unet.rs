//! The classic U-Net (Ronneberger et al. 2015), as the paper uses it (Section 4), with the
//! parameter names of the most used public PyTorch implementation (milesial/Pytorch-UNet).
//!
//! # Architecture
//!
//! - `inc`: DoubleConv(in, base). A DoubleConv is (3x3 conv without bias, BatchNorm, ReLU) twice.
//! - `down1..downD`: MaxPool 2x2 (floor, as PyTorch `MaxPool2d(2)`) then DoubleConv, doubling
//!   the width at every level: `base * 2^l`; the last one is halved with bilinear up-sampling.
//! - `up1..upD`: up-sample x2 (a 2x2 transposed convolution with bias halving the channels, or
//!   bilinear with `align_corners = true` and no parameters), zero-pad the up-sampled map to the
//!   skip's size (`[dx/2, dx - dx/2]` left/right, likewise top/bottom, as milesial's `F.pad`),
//!   concatenate `[skip, up-sampled]` (skip first), DoubleConv. With bilinear up-sampling the
//!   DoubleConv's middle width is half its input width.
//! - `outc`: 1x1 conv with bias, then the [`Head`].
//!
//! # Parameter names (one to one with milesial/Pytorch-UNet's `state_dict`)
//!
//! `inc.double_conv.{0,3}.weight` (convs), `inc.double_conv.{1,4}.{weight,bias,running_mean,
//! running_var}` (BatchNorm, eps 1e-5, momentum 0.1, weight initialised to 1 as PyTorch does),
//! `down{k}.maxpool_conv.1.double_conv.*`, `up{k}.up.{weight,bias}` (transposed only, weight
//! `[C_in, C_in / 2, 2, 2]`), `up{k}.conv.double_conv.*`, `outc.conv.{weight,bias}`. PyTorch's
//! BatchNorm also stores `num_batches_tracked`; tch does not create it (it only matters for
//! `momentum = None`), so checkpoint loading ignores it (see `train::checkpoint`). The classic
//! preset with 3 inputs and 2 classes has exactly PyTorch's 31,037,698 parameters (17,263,042
//! bilinear); tests check names and outputs against PyTorch (`tests/golden/unet_*.safetensors`).
//!
//! # Conv kinds
//!
//! Every 3x3 convolution comes from the factory [`conv2d`] with the [`ConvKind`] given at
//! construction; the network never looks at the kind. The network is built for one input size
//! `[H, W]`: level `l` runs at [`pyramid_sizes`]`[l]`, so calibrated layers get their offsets for
//! the right feature-map size (computed once, through the kernel cache). A forward pass on
//! another size is an error.

use serde::{Deserialize, Serialize};
use tch::nn::{self, Module, ModuleT};
use tch::Tensor;

use super::{conv2d, Conv, Conv2dConfig, ConvKind, ConvSite};
use crate::error::{Error, Result};
use crate::kernel::pyramid_sizes;

/// Smallest depth the depth head outputs, in metres: `depth = softplus(x) + MIN_DEPTH`, so that
/// log-depth metrics stay finite even where softplus underflows.
pub const MIN_DEPTH: f64 = 1e-3;

/// The names of the presets, in [`UNetConfig::preset`].
pub const PRESETS: [&str; 4] = ["classic", "classic-bilinear", "small", "tiny"];

/// How the decoder up-samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum UpMode {
    /// 2x2 transposed convolution, stride 2, with bias (milesial `bilinear=False`).
    Transposed,
    /// Bilinear x2 with `align_corners = true`, no parameters (milesial `bilinear=True`).
    Bilinear,
}

/// What the network predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "task")]
pub enum Head {
    /// One channel of metric depth (metres, positive): `softplus(x) + MIN_DEPTH`. Softplus
    /// rather than `exp`: positive, about linear for large `x`, so an L1 loss on metres has
    /// bounded gradients.
    Depth,
    /// Raw logits over `classes` classes (no softmax).
    Segmentation { classes: i64 },
}

impl Head {
    /// Channels of `outc`.
    pub fn channels(&self) -> i64 {
        match self {
            Head::Depth => 1,
            Head::Segmentation { classes } => *classes,
        }
    }

    /// `depth` or `segmentation`.
    pub fn task_name(&self) -> &'static str {
        match self {
            Head::Depth => "depth",
            Head::Segmentation { .. } => "segmentation",
        }
    }
}

/// The architecture (everything that decides parameter names and shapes; the input size and
/// conv kind are given when building).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UNetConfig {
    /// Input channels (3 for RGB).
    pub in_channels: i64,
    /// Width of the first level (64 in the classic U-Net).
    pub base: i64,
    /// Number of 2x2 poolings (4 in the classic U-Net).
    pub depth: usize,
    pub up: UpMode,
    pub head: Head,
}

impl UNetConfig {
    /// The classic U-Net: widths 64..1024, depth 4, transposed up-sampling, RGB input.
    pub fn classic(head: Head) -> Self {
        UNetConfig {
            in_channels: 3,
            base: 64,
            depth: 4,
            up: UpMode::Transposed,
            head,
        }
    }

    /// A named preset (see [`PRESETS`]): `classic` (base 64, depth 4, transposed),
    /// `classic-bilinear` (the same with bilinear up-sampling), `small` (base 16, depth 4) and
    /// `tiny` (base 8, depth 3) for CPU runs.
    pub fn preset(name: &str, head: Head) -> Result<Self> {
        let classic = UNetConfig::classic(head);
        match name {
            "classic" => Ok(classic),
            "classic-bilinear" => Ok(UNetConfig {
                up: UpMode::Bilinear,
                ..classic
            }),
            "small" => Ok(UNetConfig {
                base: 16,
                ..classic
            }),
            "tiny" => Ok(UNetConfig {
                base: 8,
                depth: 3,
                ..classic
            }),
            other => Err(Error::InvalidArgument(format!(
                "unknown U-Net preset `{other}` (expected one of {})",
                PRESETS.join(", ")
            ))),
        }
    }

    /// Checks the values (widths divisible as the architecture needs).
    pub fn check(&self) -> Result<()> {
        if self.in_channels < 1 || self.depth < 1 || self.head.channels() < 1 {
            return Err(Error::InvalidArgument(format!(
                "U-Net needs in_channels, depth and output channels >= 1: {self:?}"
            )));
        }
        let min_base = if self.up == UpMode::Bilinear { 2 } else { 1 };
        if self.base < min_base {
            return Err(Error::InvalidArgument(format!(
                "U-Net base width must be >= {min_base}: {self:?}"
            )));
        }
        Ok(())
    }

    /// Width of encoder level `l` (`0..=depth`) as written: `base * 2^l`, the deepest halved
    /// with bilinear up-sampling.
    pub fn level_width(&self, l: usize) -> i64 {
        let w = self.base << l;
        if l == self.depth && self.up == UpMode::Bilinear {
            w / 2
        } else {
            w
        }
    }
}

fn batch_norm(p: &nn::Path, c: i64) -> nn::BatchNorm {
    nn::batch_norm2d(
        p,
        c,
        nn::BatchNormConfig {
            eps: 1e-5,
            momentum: 0.1,
            // PyTorch initialises the scale to 1 (tch's default is U(0, 1)).
            ws_init: nn::Init::Const(1.0),
            bs_init: nn::Init::Const(0.0),
            ..Default::default()
        },
    )
}

/// (3x3 conv without bias, BatchNorm, ReLU) twice, under `P.double_conv.{0,1,3,4}`.
#[derive(Debug)]
pub struct DoubleConv {
    conv1: Conv,
    bn1: nn::BatchNorm,
    conv2: Conv,
    bn2: nn::BatchNorm,
}

impl DoubleConv {
    /// A DoubleConv `c_in -> mid -> c_out` for an input feature map of `size` `[H, W]`; its
    /// first convolution sits at `site`, both at pyramid `level`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        p: &nn::Path,
        c_in: i64,
        mid: i64,
        c_out: i64,
        kind: &ConvKind,
        size: [i64; 2],
        site: ConvSite,
        level: usize,
    ) -> Result<Self> {
        let p = p / "double_conv";
        let cfg = Conv2dConfig {
            bias: false,
            level,
            ..Default::default()
        };
        let first = Conv2dConfig { site, ..cfg };
        Ok(DoubleConv {
            conv1: conv2d(&(&p / 0), c_in, mid, 3, kind, size, first)?,
            bn1: batch_norm(&(&p / 1), mid),
            conv2: conv2d(&(&p / 3), mid, c_out, 3, kind, size, cfg)?,
            bn2: batch_norm(&(&p / 4), c_out),
        })
    }
}

impl ModuleT for DoubleConv {
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]` (the size the block was built for)
    /// - output: `[B, C_out, H, W]`
    fn forward_t(&self, xs: &Tensor, train: bool) -> Tensor {
        let x = self.bn1.forward_t(&self.conv1.forward(xs), train).relu();
        self.bn2.forward_t(&self.conv2.forward(&x), train).relu()
    }
}

/// Decoder block: up-sample, pad, concatenate `[skip, up]`, DoubleConv.
#[derive(Debug)]
struct Up {
    /// `None`: bilinear.
    up: Option<nn::ConvTranspose2D>,
    conv: DoubleConv,
}

impl Up {
    /// The decoder block that takes level `l + 1` of `config` to level `l` (feature map `size`),
    /// under `p` (`up{k}`).
    fn new(
        p: &nn::Path,
        config: &UNetConfig,
        l: usize,
        kind: &ConvKind,
        size: [i64; 2],
    ) -> Result<Self> {
        let c_in = config.base << (l + 1);
        let c_out = match (config.up, l) {
            (UpMode::Bilinear, l) if l > 0 => (config.base << l) / 2,
            _ => config.base << l,
        };
        let (up, mid) = match config.up {
            UpMode::Transposed => (
                Some(nn::conv_transpose2d(
                    p / "up",
                    c_in,
                    c_in / 2,
                    2,
                    nn::ConvTransposeConfig {
                        stride: 2,
                        ..Default::default()
                    },
                )),
                c_out,
            ),
            UpMode::Bilinear => (None, c_in / 2),
        };
        let conv = DoubleConv::new(
            &(p / "conv"),
            c_in,
            mid,
            c_out,
            kind,
            size,
            ConvSite::AfterSkip,
            l,
        )?;
        Ok(Up { up, conv })
    }

    fn forward_t(&self, x: &Tensor, skip: &Tensor, train: bool) -> Tensor {
        let x = match &self.up {
            Some(t) => t.forward(x),
            None => {
                let s = x.size();
                x.upsample_bilinear2d([2 * s[2], 2 * s[3]], true, None, None)
            }
        };
        let (s, u) = (skip.size(), x.size());
        let (dy, dx) = (s[2] - u[2], s[3] - u[3]);
        let x = if dy != 0 || dx != 0 {
            x.constant_pad_nd([dx / 2, dx - dx / 2, dy / 2, dy - dy / 2])
        } else {
            x
        };
        self.conv.forward_t(&Tensor::cat(&[skip, &x], 1), train)
    }
}

/// `r` with its error naming U-Net level `l` of `sizes`.
fn at_level<T>(sizes: &[[i64; 2]], l: usize, r: Result<T>) -> Result<T> {
    r.map_err(|e| {
        Error::InvalidArgument(format!(
            "U-Net level {l} ({}x{}): {e}",
            sizes[l][0], sizes[l][1]
        ))
    })
}

/// The U-Net, built for one input size and conv kind.
#[derive(Debug)]
pub struct UNet {
    config: UNetConfig,
    input_size: [i64; 2],
    inc: DoubleConv,
    downs: Vec<DoubleConv>,
    ups: Vec<Up>,
    outc: Conv,
}

impl UNet {
    /// Builds the network under `vs` for inputs of `input_size` `[H, W]`, with every 3x3
    /// convolution of `kind`. Fails if the configuration is invalid, if the deepest level would
    /// be empty, or if a calibrated layer cannot be built for its level (e.g. a feature map too
    /// small for the camera's field of view); the error names the level.
    pub fn new(
        vs: &nn::Path,
        config: &UNetConfig,
        kind: &ConvKind,
        input_size: [i64; 2],
    ) -> Result<Self> {
        config.check()?;
        let d = config.depth;
        if input_size.iter().any(|&s| s < 1) {
            return Err(Error::InvalidArgument(format!(
                "U-Net input size must be positive, got {input_size:?}"
            )));
        }
        let sizes: Vec<[i64; 2]> =
            pyramid_sizes([input_size[0] as usize, input_size[1] as usize], d)
                .into_iter()
                .map(|s| [s[0] as i64, s[1] as i64])
                .collect();
        if sizes[d].iter().any(|&s| s < 1) {
            return Err(Error::InvalidArgument(format!(
                "a {}x{} input is too small for a U-Net of depth {d} (level {d} would be {}x{})",
                input_size[0], input_size[1], sizes[d][0], sizes[d][1]
            )));
        }
        let w = |l: usize| config.level_width(l);
        let inc = at_level(
            &sizes,
            0,
            DoubleConv::new(
                &(vs / "inc"),
                config.in_channels,
                w(0),
                w(0),
                kind,
                sizes[0],
                ConvSite::Body,
                0,
            ),
        )?;
        let mut downs = Vec::with_capacity(d);
        for (l, &size) in sizes.iter().enumerate().skip(1) {
            let p = vs / format!("down{l}") / "maxpool_conv" / 1;
            downs.push(at_level(
                &sizes,
                l,
                DoubleConv::new(&p, w(l - 1), w(l), w(l), kind, size, ConvSite::Body, l),
            )?);
        }
        let mut ups = Vec::with_capacity(d);
        for k in 1..=d {
            // Up k takes level d-k+1 to level d-k.
            let l = d - k;
            let p = vs / format!("up{k}");
            ups.push(at_level(&sizes, l, Up::new(&p, config, l, kind, sizes[l]))?);
        }
        let outc = conv2d(
            &(vs / "outc" / "conv"),
            w(0),
            config.head.channels(),
            1,
            kind,
            sizes[0],
            Conv2dConfig::default(),
        )?;
        Ok(UNet {
            config: *config,
            input_size,
            inc,
            downs,
            ups,
            outc,
        })
    }

    /// The architecture.
    pub fn config(&self) -> &UNetConfig {
        &self.config
    }

    /// The input size `[H, W]` the network was built for.
    pub fn input_size(&self) -> [i64; 2] {
        self.input_size
    }

    fn check_input(&self, xs: &Tensor) -> Result<()> {
        let s = xs.size();
        let want = [
            self.config.in_channels,
            self.input_size[0],
            self.input_size[1],
        ];
        if s.len() != 4 || s[1..] != want {
            return Err(Error::InvalidArgument(format!(
                "U-Net built for inputs [B, {}, {}, {}], got {s:?}",
                want[0], want[1], want[2]
            )));
        }
        Ok(())
    }

    /// The output of `outc` before the head (raw logits for segmentation, the pre-activation
    /// for depth): what milesial's `UNet.forward` returns.
    ///
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]`, `[H, W]` the size the network was built for
    /// - output: `[B, C_head, H, W]`
    pub fn f_forward_raw_t(&self, xs: &Tensor, train: bool) -> Result<Tensor> {
        self.check_input(xs)?;
        let mut skips = Vec::with_capacity(self.downs.len() + 1);
        let mut x = self.inc.forward_t(xs, train);
        for down in &self.downs {
            let pooled = x.max_pool2d([2, 2], [2, 2], [0, 0], [1, 1], false);
            skips.push(x);
            x = down.forward_t(&pooled, train);
        }
        for up in &self.ups {
            let skip = skips.pop().expect("one skip per level");
            x = up.forward_t(&x, &skip, train);
        }
        Ok(self.outc.forward(&x))
    }

    /// The prediction: depth in metres (`softplus(x) + MIN_DEPTH`) or segmentation logits.
    ///
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]` float, `[H, W]` the size the network was built for
    /// - output: `[B, 1, H, W]` depth (metres, > 0) or `[B, classes, H, W]` logits
    pub fn f_forward_t(&self, xs: &Tensor, train: bool) -> Result<Tensor> {
        let raw = self.f_forward_raw_t(xs, train)?;
        Ok(match self.config.head {
            Head::Depth => raw.softplus() + MIN_DEPTH,
            Head::Segmentation { .. } => raw,
        })
    }
}

impl ModuleT for UNet {
    /// [`UNet::f_forward_t`]; panics with its message on an input of the wrong shape.
    ///
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]`
    /// - output: `[B, 1, H, W]` (depth) or `[B, classes, H, W]` (logits)
    fn forward_t(&self, xs: &Tensor, train: bool) -> Tensor {
        self.f_forward_t(xs, train)
            .unwrap_or_else(|e| panic!("UNet: {e}"))
    }
}

#[cfg(test)]
mod tests {
    use tch::nn::VarStore;
    use tch::{Device, Kind};

    use super::*;
    use crate::nn::tests::{calibrated, f195, names_and_shapes};

    fn kinds() -> Vec<(&'static str, ConvKind)> {
        vec![
            ("standard", ConvKind::Standard),
            ("calibrated", calibrated(f195())),
            (
                "camconv",
                ConvKind::CamConv {
                    camera: std::sync::Arc::new(f195()),
                    frame: Default::default(),
                },
            ),
            (
                "calibrated-learned",
                ConvKind::CalibratedLearned {
                    camera: std::sync::Arc::new(f195()),
                    frame: Default::default(),
                },
            ),
        ]
    }

    #[test]
    fn every_kind_and_preset_gives_the_right_shape_finite_output_and_all_gradients() {
        // 64x56 keeps the deepest level of depth-4 presets at 4x3 px: wide enough for F195
        // calibrated kernels (a 3-tap kernel must see < 178 deg: 3 * 195 / 4 = 146 deg).
        let size = [56i64, 64];
        for (kind_name, kind) in kinds() {
            for preset in PRESETS {
                for head in [Head::Depth, Head::Segmentation { classes: 5 }] {
                    let what = format!("{preset} / {kind_name} / {head:?}");
                    tch::manual_seed(0);
                    let vs = VarStore::new(Device::Cpu);
                    let cfg = UNetConfig::preset(preset, head).unwrap();
                    let net = UNet::new(&vs.root(), &cfg, &kind, size).unwrap();
                    let x = Tensor::rand([2, 3, size[0], size[1]], (Kind::Float, Device::Cpu));
                    let y = net.f_forward_t(&x, true).unwrap();
                    assert_eq!(y.size(), [2, head.channels(), size[0], size[1]], "{what}");
                    assert_eq!(y.isfinite().all().int64_value(&[]), 1, "{what}");
                    if head == Head::Depth {
                        assert!(
                            y.min().double_value(&[]) >= MIN_DEPTH as f32 as f64,
                            "{what}"
                        );
                    }
                    // A loss that depends on every output pixel and channel.
                    (&y * Tensor::randn_like(&y)).sum(Kind::Float).backward();
                    for (name, var) in vs.variables() {
                        if !var.requires_grad() {
                            continue; // BatchNorm running statistics
                        }
                        let g = var.grad();
                        assert!(g.defined(), "{what}: {name} has no gradient");
                        assert_eq!(g.isfinite().all().int64_value(&[]), 1, "{what}: {name}");
                        assert!(
                            g.abs().max().double_value(&[]) > 0.0,
                            "{what}: {name} has an all-zero gradient"
                        );
                    }
                    if preset.starts_with("classic") {
                        break; // one head is enough for the 31M-parameter presets
                    }
                }
            }
        }
    }

    #[test]
    fn classic_has_the_pytorch_parameter_count_and_names() {
        // milesial/Pytorch-UNet UNet(3, 2): 31,037,698 parameters (transposed), 17,263,042
        // (bilinear); 118 / 110 state_dict keys of which 18 are BatchNorm num_batches_tracked.
        for (preset, params, keys) in [
            ("classic", 31_037_698i64, 118 - 18),
            ("classic-bilinear", 17_263_042, 110 - 18),
        ] {
            let vs = VarStore::new(Device::Cpu);
            let cfg = UNetConfig::preset(preset, Head::Segmentation { classes: 2 }).unwrap();
            UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [64, 64]).unwrap();
            let vars = vs.variables();
            assert_eq!(vars.len(), keys, "{preset}");
            let n: i64 = vars
                .values()
                .filter(|t| t.requires_grad())
                .map(|t| t.numel() as i64)
                .sum();
            assert_eq!(n, params, "{preset}");
            for name in [
                "inc.double_conv.0.weight",
                "inc.double_conv.1.running_var",
                "down4.maxpool_conv.1.double_conv.4.bias",
                "up1.conv.double_conv.3.weight",
                "outc.conv.bias",
            ] {
                assert!(vars.contains_key(name), "{preset}: no {name}");
            }
            assert_eq!(
                vars.contains_key("up1.up.weight"),
                preset == "classic",
                "{preset}"
            );
        }
    }

    #[test]
    fn a_standard_checkpoint_loads_into_a_calibrated_network_unchanged() {
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let build = |kind: &ConvKind| {
            let vs = VarStore::new(Device::Cpu);
            let net = UNet::new(&vs.root(), &cfg, kind, [48, 40]).unwrap();
            (vs, net)
        };
        let kinds = kinds();
        let (vs_std, net_std) = build(&kinds[0].1);
        let (vs_cal, net_cal) = build(&kinds[1].1);
        assert_eq!(names_and_shapes(&vs_std), names_and_shapes(&vs_cal));
        // Through a checkpoint file, as a fine-tuning run starts from a baseline.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bl.safetensors");
        let vars = crate::train::checkpoint::named_variables(&vs_std);
        crate::train::checkpoint::write_tensors(&path, &vars, Default::default()).unwrap();
        crate::train::checkpoint::load(&path, &vs_cal, &cfg).unwrap();
        for (name, t) in vs_std.variables() {
            assert!(vs_cal.variables()[&name].equal(&t), "{name}");
        }
        // Same weights, calibrated sampling: another function of the input.
        let x = Tensor::rand([1, 3, 48, 40], (Kind::Float, Device::Cpu));
        let (a, b) = (
            net_std.f_forward_t(&x, false).unwrap(),
            net_cal.f_forward_t(&x, false).unwrap(),
        );
        assert!((a - b).abs().max().double_value(&[]) > 1e-4);
    }

    /// The kinds beyond the paper's two start, from a checkpoint without their added
    /// parameters, as the network the checkpoint was trained as: camconv exactly as the standard
    /// network (its map weights are zero), calibrated-learned as the calibrated one (its offset
    /// branch outputs zero; the sampled op rounds differently from the planned one).
    #[test]
    fn added_kinds_start_as_the_network_their_checkpoint_comes_from() {
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let size = [48i64, 40];
        let build = |kind: &ConvKind| {
            let vs = VarStore::new(Device::Cpu);
            let net = UNet::new(&vs.root(), &cfg, kind, size).unwrap();
            (vs, net)
        };
        let kinds = kinds();
        tch::manual_seed(5);
        let (vs_std, net_std) = build(&kinds[0].1);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bl.safetensors");
        let vars = crate::train::checkpoint::named_variables(&vs_std);
        crate::train::checkpoint::write_tensors(&path, &vars, Default::default()).unwrap();
        let x = Tensor::rand([2, 3, size[0], size[1]], (Kind::Float, Device::Cpu));
        let out = |net: &UNet| net.f_forward_t(&x, false).unwrap();
        let (vs_cal, net_cal) = build(&kinds[1].1);
        crate::train::checkpoint::load(&path, &vs_cal, &cfg).unwrap();
        for (reference, (name, kind)) in [(&net_std, &kinds[2]), (&net_cal, &kinds[3])] {
            let (vs, net) = build(kind);
            let added: Vec<String> = names_and_shapes(&vs)
                .into_iter()
                .map(|(n, _)| n)
                .filter(|n| crate::nn::is_added_parameter(n))
                .collect();
            assert!(!added.is_empty(), "{name} adds no parameters");
            // Strict loading names them; loading starting weights leaves them at zero.
            let err = crate::train::checkpoint::load(&path, &vs, &cfg)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("missing from the file") && err.contains(".added."),
                "{err}"
            );
            crate::train::checkpoint::load_init(&path, &vs, &cfg).unwrap();
            for n in &added {
                let t = &vs.variables()[n];
                assert_eq!(t.abs().max().double_value(&[]), 0.0, "{name}: {n}");
            }
            let diff = (out(&net) - out(reference)).abs().max().double_value(&[]);
            let tol = if *name == "camconv" { 0.0 } else { 1e-4 };
            assert!(diff <= tol, "{name}: {diff}");
        }
        // The CAM maps sit after the skip connections only: one map weight per decoder block.
        let (vs_cam, _) = build(&kinds[2].1);
        let maps: Vec<String> = names_and_shapes(&vs_cam)
            .into_iter()
            .map(|(n, _)| n)
            .filter(|n| n.ends_with("added.cam_maps.weight"))
            .collect();
        assert_eq!(maps.len(), cfg.depth, "{maps:?}");
        assert!(
            maps.iter().all(|n| n.contains(".conv.double_conv.0.")),
            "{maps:?}"
        );
    }

    #[test]
    fn odd_input_sizes_are_padded_in_the_decoder() {
        let vs = VarStore::new(Device::Cpu);
        for up in [UpMode::Transposed, UpMode::Bilinear] {
            let cfg = UNetConfig {
                up,
                ..UNetConfig::preset("tiny", Head::Depth).unwrap()
            };
            let net = UNet::new(
                &(vs.root() / format!("{up:?}")),
                &cfg,
                &ConvKind::Standard,
                [37, 45],
            )
            .unwrap();
            let y = net
                .f_forward_t(
                    &Tensor::rand([1, 3, 37, 45], (Kind::Float, Device::Cpu)),
                    false,
                )
                .unwrap();
            assert_eq!(y.size(), [1, 1, 37, 45]);
        }
    }

    #[test]
    fn wrong_input_size_and_too_deep_networks_are_errors() {
        let vs = VarStore::new(Device::Cpu);
        let cfg = UNetConfig::preset("tiny", Head::Depth).unwrap();
        let net = UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [32, 32]).unwrap();
        let err = net
            .f_forward_t(
                &Tensor::zeros([1, 3, 32, 40], (Kind::Float, Device::Cpu)),
                false,
            )
            .unwrap_err();
        assert!(err.to_string().contains("[B, 3, 32, 32]"), "{err}");
        let err = UNet::new(&(vs.root() / "x"), &cfg, &ConvKind::Standard, [4, 32]).unwrap_err();
        assert!(err.to_string().contains("too small"), "{err}");
        // A 16x16 input leaves 2 px at level 3: too narrow for a 195 deg calibrated kernel.
        let err = UNet::new(&(vs.root() / "y"), &cfg, &kinds()[1].1, [16, 16]).unwrap_err();
        assert!(err.to_string().contains("level 3 (2x2)"), "{err}");
        assert!(UNetConfig::preset("huge", Head::Depth).is_err());
    }
}
