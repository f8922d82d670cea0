//! The layout of a CPU `CalibratedConv2d`'s output: channels-last, but NCHW with fewer than 16
//! outputs when libtorch runs more than one thread (its channels-last batch norm is several
//! times slower there; `NCHW_BELOW_CHANNELS` in src/nn/calibrated.rs). A test binary of its own:
//! it sets the process's libtorch thread count.

use tch::nn::{Module, VarStore};
use tch::{Device, Kind, Tensor};

use calibconv::camera;
use calibconv::kernel::InputFrame;
use calibconv::nn::{CalibratedConv2d, Conv2dConfig};

fn is_channels_last(x: &Tensor) -> bool {
    let (_, c, h, w) = x.size4().unwrap();
    x.stride() == [h * w * c, 1, w * c, c]
}

#[test]
fn few_outputs_are_nchw_with_several_threads_and_the_values_do_not_change() {
    let cam = camera::load(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/cameras/f195.toml"
    ))
    .unwrap();
    let vs = VarStore::new(Device::Cpu);
    let size = [24i64, 20];
    let threads = tch::get_num_threads();
    tch::manual_seed(5);
    for (c_in, c_out, nchw_at_two) in [(3, 8, true), (16, 8, true), (8, 16, false)] {
        let conv = CalibratedConv2d::new(
            &(vs.root() / format!("conv{c_in}_{c_out}")),
            c_in,
            c_out,
            3,
            &cam,
            &InputFrame::default(),
            size,
            Conv2dConfig::default(),
        )
        .unwrap();
        // NCHW and channels-last inputs (the layer after a channels-last one gets the latter)
        let x = Tensor::randn([2, c_in, size[0], size[1]], (Kind::Float, Device::Cpu));
        let x_cl = x
            .contiguous()
            .permute([0, 2, 3, 1])
            .contiguous()
            .permute([0, 3, 1, 2]);
        for input in [&x, &x_cl] {
            tch::set_num_threads(1);
            let one = conv.forward(input);
            tch::set_num_threads(2);
            let two = conv.forward(input);
            tch::set_num_threads(threads);
            let what = format!(
                "{c_in}->{c_out}, input channels-last {}",
                is_channels_last(input)
            );
            assert!(
                is_channels_last(&one),
                "{what}: one thread: channels-last output"
            );
            if nchw_at_two {
                assert!(two.is_contiguous(), "{what}: two threads: NCHW output");
            } else {
                assert!(
                    is_channels_last(&two),
                    "{what}: two threads: channels-last output"
                );
            }
            assert!(one.equal(&two), "{what}: the values depend on the layout");
        }
    }
}
