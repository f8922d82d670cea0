//! The layout of a CPU `CalibratedConv2d`'s output: channels-last, but NCHW with fewer than 16
//! outputs when libtorch runs more than one thread (its channels-last batch norm is several
//! times slower there; `NCHW_BELOW_CHANNELS` in src/nn/calibrated.rs). A test binary of its own:
//! it sets the process's libtorch thread count.

use tch::nn::{Module, VarStore};
use tch::{Device, Kind, Tensor};

use calibconv::camera;
use calibconv::kernel::InputFrame;
use calibconv::nn::{CalibratedConv2d, CameraInput, Conv2dConfig};

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
            CameraInput::new(&cam, &InputFrame::default(), size),
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
        // the same output gradient for both runs, in neither output's layout
        let r = Tensor::randn([2, c_out, size[0], size[1]], (Kind::Float, Device::Cpu));
        for input in [&x, &x_cl] {
            // forward and backward at n threads: the output, and the input's and the weight's
            // gradients
            let run = |n: usize| {
                tch::set_num_threads(n as i32);
                let leaf = input.detach().set_requires_grad(true);
                let y = conv.forward(&leaf);
                for p in vs.trainable_variables() {
                    let mut g = p.grad();
                    if g.defined() {
                        let _ = g.zero_();
                    }
                }
                (&y * &r).sum(Kind::Float).backward();
                let w = vs
                    .variables()
                    .into_iter()
                    .find(|(name, _)| name == &format!("conv{c_in}_{c_out}.weight"))
                    .expect("the layer's weight")
                    .1
                    .grad()
                    .copy();
                (y.detach(), leaf.grad(), w)
            };
            let (one, gx_one, gw_one) = run(1);
            let (two, gx_two, gw_two) = run(2);
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
            // The input gradient's scatter adds in an order of its own, whatever the thread count
            // and the output gradient's layout; the weight gradient's chunks depend on the thread
            // count.
            assert!(
                gx_one.equal(&gx_two),
                "{what}: the input gradient depends on the layout"
            );
            // (float32 sums of 960 products in another order: tolerance scaled to the largest)
            let scale = gw_one.abs().max().double_value(&[]);
            assert!(
                gw_one.allclose(&gw_two, 1e-5, 1e-5 * scale, false),
                "{what}: the weight gradient depends on the layout"
            );
        }
    }
}
