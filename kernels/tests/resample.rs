//! The U-Net's resampling ops against burn's own: `max_pool2` against `max_pool2d` (2×2,
//! stride 2) and `upsample2` against a reshape + `repeat_dim`, values and gradients through
//! autodiff.

use burn::tensor::module::max_pool2d;
use burn::tensor::ops::MaxPoolOptions;
use burn::tensor::{Device, Distribution, Tensor};
use tcsense_kernels::resample::{max_pool2, upsample2};

fn max_abs_diff<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
    (a - b).abs().max().into_scalar::<f32>()
}

fn repeat_up(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h, 1, w, 1]).repeat_dim(3, 2).repeat_dim(5, 2).reshape([b, c, 2 * h, 2 * w])
}

#[test]
fn pooling_and_upsampling_equal_burns() {
    let device = Device::flex().autodiff();
    for [b, c, h, w] in [[1, 1, 2, 2], [2, 3, 6, 10], [1, 8, 18, 22]] {
        let x = Tensor::<4>::random([b, c, h, w], Distribution::Normal(0.0, 1.0), &device).require_grad();
        let g = Tensor::<4>::random([b, c, h / 2, w / 2], Distribution::Normal(0.0, 1.0), &device);
        let (ours, theirs) = (max_pool2(x.clone()), max_pool2d(x.clone(), MaxPoolOptions::new([2, 2])));
        assert_eq!(max_abs_diff(ours.clone(), theirs.clone()), 0.0, "max-pool values at {b}x{c}x{h}x{w}");
        let (go, gt) = ((ours * g.clone()).sum().backward(), (theirs * g).sum().backward());
        assert_eq!(max_abs_diff(x.grad(&go).expect("grad"), x.grad(&gt).expect("grad")), 0.0, "max-pool gradient");

        let g2 = Tensor::<4>::random([b, c, 2 * h, 2 * w], Distribution::Normal(0.0, 1.0), &device);
        let (ours, theirs) = (upsample2(x.clone()), repeat_up(x.clone()));
        assert_eq!(max_abs_diff(ours.clone(), theirs.clone()), 0.0, "up-sample values");
        let (go, gt) = ((ours * g2.clone()).sum().backward(), (theirs * g2).sum().backward());
        let diff = max_abs_diff(x.grad(&go).expect("grad"), x.grad(&gt).expect("grad"));
        assert!(diff < 1e-5, "up-sample gradient differs by {diff}");
    }
    // without autodiff too
    let flex = Device::flex();
    let x = Tensor::<4>::from_floats([[[[1.0, 5.0, 2.0, 0.0], [3.0, 4.0, 7.0, 7.0]]]], &flex); // [1, 1, 2, 4]
    assert_eq!(max_pool2(x.clone()).into_data().try_into_vec::<f32>().unwrap_or_default(), vec![5.0, 7.0]);
    assert_eq!(upsample2(x).dims(), [1, 1, 4, 8]);
}
