//! The custom 3×3 conv op against burn's own `conv2d`: same values forward, same gradients for
//! the input, the kernel and the bias through autodiff, with and without autodiff on.

use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::Device;
use burn::tensor::{Distribution, Tensor};
use tcsense_kernels::conv_op::conv3x3;

fn max_abs_diff<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
    (a - b).abs().max().into_scalar::<f32>()
}

fn scale<const D: usize>(a: &Tensor<D>) -> f32 {
    a.clone().abs().max().into_scalar::<f32>().max(1e-6)
}

#[test]
fn forward_and_gradients_equal_burns_conv2d() {
    // (B, C_in, C_out, H, W): odd sizes, a single row, a single column, a large frame, and
    // 3 bands of rows per item (9·32 + 1 im2col rows × 100 columns)
    for &(b, ci, co, h, w) in &[(2, 3, 5, 7, 6), (1, 4, 2, 1, 9), (2, 2, 3, 9, 1), (1, 2, 2, 70, 100), (2, 32, 3, 20, 100)] {
        let device = Device::flex().autodiff();
        let x = Tensor::<4>::random([b, ci, h, w], Distribution::Normal(0.0, 1.0), &device).require_grad();
        let k = Tensor::<4>::random([co, ci, 3, 3], Distribution::Normal(0.0, 0.3), &device).require_grad();
        let bias = Tensor::<1>::random([co], Distribution::Normal(0.0, 1.0), &device).require_grad();
        // a loss that weights every output element differently
        let wts = Tensor::<4>::random([b, co, h, w], Distribution::Normal(0.0, 1.0), &device);

        let ours = conv3x3(x.clone(), k.clone(), bias.clone());
        let theirs = conv2d(x.clone(), k.clone(), Some(bias.clone()), ConvOptions::new([1, 1], [1, 1], [1, 1], 1));
        let s = scale(&theirs);
        let e = max_abs_diff(ours.clone(), theirs.clone());
        assert!(e <= 1e-5 * s, "{:?}: forward differs by {e} (scale {s})", (b, ci, co, h, w));

        let g_ours = (ours * wts.clone()).sum().backward();
        let g_theirs = (theirs * wts).sum().backward();
        for (name, a, t) in
            [("x", x.grad(&g_ours).unwrap(), x.grad(&g_theirs).unwrap()), ("kernel", k.grad(&g_ours).unwrap(), k.grad(&g_theirs).unwrap())]
        {
            let s = scale(&t);
            let e = max_abs_diff(a, t);
            assert!(e <= 1e-4 * s, "{:?}: d{name} differs by {e} (scale {s})", (b, ci, co, h, w));
        }
        let (a, t) = (bias.grad(&g_ours).unwrap(), bias.grad(&g_theirs).unwrap());
        let e = max_abs_diff(a, t.clone());
        assert!(e <= 1e-4 * scale(&t), "dbias differs by {e}");

        // and without autodiff
        let plain = Device::flex();
        let x = Tensor::<4>::random([b, ci, h, w], Distribution::Normal(0.0, 1.0), &plain);
        let k = Tensor::<4>::random([co, ci, 3, 3], Distribution::Normal(0.0, 0.3), &plain);
        let bias = Tensor::<1>::random([co], Distribution::Normal(0.0, 1.0), &plain);
        let theirs = conv2d(x.clone(), k.clone(), Some(bias.clone()), ConvOptions::new([1, 1], [1, 1], [1, 1], 1));
        let e = max_abs_diff(conv3x3(x, k, bias), theirs.clone());
        assert!(e <= 1e-5 * scale(&theirs), "inference forward differs by {e}");
    }
}

/// A strided (permuted) input is made contiguous, not read with the wrong strides.
#[test]
fn strided_input_is_read_correctly() {
    let device = Device::flex();
    let base = Tensor::<4>::random([2, 5, 6, 3], Distribution::Normal(0.0, 1.0), &device);
    let x = base.permute([0, 3, 1, 2]); // [2, 3, 5, 6], not contiguous
    let k = Tensor::<4>::random([4, 3, 3, 3], Distribution::Normal(0.0, 0.3), &device);
    let bias = Tensor::<1>::zeros([4], &device);
    let theirs = conv2d(x.clone(), k.clone(), Some(bias.clone()), ConvOptions::new([1, 1], [1, 1], [1, 1], 1));
    let e = max_abs_diff(conv3x3(x, k, bias), theirs.clone());
    assert!(e <= 1e-5 * scale(&theirs), "strided forward differs by {e}");
}
