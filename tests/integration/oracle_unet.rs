//! The U-Net against PyTorch: a milesial/Pytorch-UNet-layout `state_dict` (the reference network
//! of `tools/reference_unet.py`, written by `tools/make_unet_fixture.py`, `num_batches_tracked`
//! included) loads by name into `calibconv::nn::UNet`, and the outputs match in eval and train
//! mode, as do the BatchNorm running statistics after one training-mode forward (momentum 0.1).
//! `tests/integration/pytorch_parity.rs` covers conversion from `.pth` and export back; this file
//! covers training-mode behaviour.

use std::sync::Arc;

use tch::nn::VarStore;
use tch::Device;

use calibconv::kernel::InputFrame;
use calibconv::nn::{ConvKind, Head, UNet, UNetConfig, UpMode};
use calibconv::train::checkpoint;

use crate::common::{golden, max_rel, read_safetensors};

/// float32 convolutions and BatchNorm run by the same libtorch from two front ends. Observed:
/// bit-identical; the margin is for other thread counts / kernels, which reorder float32 sums.
const TOL: f64 = 1e-5;

fn config(up: UpMode) -> UNetConfig {
    UNetConfig {
        in_channels: 3,
        base: 4,
        depth: 4,
        up,
        head: Head::Segmentation { classes: 4 },
    }
}

#[test]
fn pytorch_state_dicts_load_by_name_and_give_pytorchs_outputs() {
    for (mode, up) in [
        ("transposed", UpMode::Transposed),
        ("bilinear", UpMode::Bilinear),
    ] {
        let weights = golden(&format!("unet_tiny_{mode}.safetensors"));
        let io = read_safetensors(&golden(&format!("unet_tiny_{mode}_io.safetensors")));
        let cfg = config(up);
        let vs = VarStore::new(Device::Cpu);
        let net = UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [37, 69]).unwrap();
        let loaded = checkpoint::load(&weights, &vs, &cfg).unwrap();
        assert!(loaded.info.is_none());
        // 2 BatchNorms per DoubleConv, 1 + 2 * depth DoubleConvs: milesial's 18.
        assert_eq!(loaded.ignored.len(), 18, "{mode}: {:?}", loaded.ignored);

        let x = &io["input"];
        let eval = tch::no_grad(|| net.f_forward_raw_t(x, false)).unwrap();
        let e = max_rel(&eval, &io["output_eval"]);
        assert!(e < TOL, "{mode} eval: {e}");
        let train = tch::no_grad(|| net.f_forward_raw_t(x, true)).unwrap();
        let e = max_rel(&train, &io["output_train"]);
        assert!(e < TOL, "{mode} train: {e}");
        let vars = vs.variables();
        for (name, key) in [
            ("inc.double_conv.1.running_mean", "running_mean_after"),
            ("inc.double_conv.1.running_var", "running_var_after"),
        ] {
            let e = max_rel(&vars[name], &io[key]);
            assert!(e < TOL, "{mode} {name}: {e}");
        }
    }
}

#[test]
fn the_same_pytorch_weights_load_into_a_calibrated_network() {
    let camera = calibconv::camera::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/cameras/f195.toml"
    ))
    .unwrap();
    let kind = ConvKind::Calibrated {
        camera: Arc::new(camera),
        frame: InputFrame::default(),
    };
    let cfg = config(UpMode::Transposed);
    let vs = VarStore::new(Device::Cpu);
    let net = UNet::new(&vs.root(), &cfg, &kind, [37, 69]).unwrap();
    checkpoint::load(&golden("unet_tiny_transposed.safetensors"), &vs, &cfg).unwrap();
    let io = read_safetensors(&golden("unet_tiny_transposed_io.safetensors"));
    let y = tch::no_grad(|| net.f_forward_raw_t(&io["input"], false)).unwrap();
    assert_eq!(y.size(), io["output_eval"].size());
    // Same weights, other sampling: the outputs differ (calibrated kernels are really used).
    assert!(max_rel(&y, &io["output_eval"]) > 1e-3);
}

#[test]
fn a_pytorch_checkpoint_for_another_architecture_names_the_mismatching_tensors() {
    let cfg = UNetConfig {
        base: 8,
        ..config(UpMode::Transposed)
    };
    let vs = VarStore::new(Device::Cpu);
    UNet::new(&vs.root(), &cfg, &ConvKind::Standard, [37, 69]).unwrap();
    let path = golden("unet_tiny_transposed.safetensors");
    let err = checkpoint::load(&path, &vs, &cfg).unwrap_err().to_string();
    assert!(err.contains("unet_tiny_transposed.safetensors"), "{err}");
    assert!(
        err.contains("`down1.maxpool_conv.1.double_conv.0.weight`: [8, 4, 3, 3] in the file, [16, 8, 3, 3] in the network"),
        "{err}"
    );
    // The bilinear file lacks the transposed convolutions.
    let err = checkpoint::load(&golden("unet_tiny_bilinear.safetensors"), &vs, &cfg)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("missing from the file: `up1.up.bias`"),
        "{err}"
    );
}
