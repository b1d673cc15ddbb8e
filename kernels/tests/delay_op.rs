//! The delay-tap convolution op against its composed form built from burn's own ops
//! (`roll_dim` + `cat` into `[B·T, 3·C_in, H, W]`, then burn's `conv2d`): the same values
//! forward, the same gradients for the input, the kernel and the bias through autodiff, for
//! dilations 1, 3 and 9 and 4 to 256 bins.

use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Distribution, Tensor};
use tcsense_kernels::delay_op::{delay_conv3x3, delay_conv3x3_composed, delay_taps};

fn max_abs_diff<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
    (a - b).abs().max().into_scalar::<f32>()
}

fn scale<const D: usize>(a: &Tensor<D>) -> f32 {
    a.clone().abs().max().into_scalar::<f32>().max(1e-6)
}

/// The reference: the stacked taps through burn's generic conv2d (no kernel of ours).
fn reference(x: Tensor<5>, k: Tensor<4>, bias: Tensor<1>, d: usize) -> Tensor<5> {
    let [b, t, c, h, w] = x.dims();
    let co = k.dims()[0];
    let taps = delay_taps(x, d).reshape([b * t, 3 * c, h, w]);
    conv2d(taps, k, Some(bias), ConvOptions::new([1, 1], [1, 1], [1, 1], 1)).reshape([b, t, co, h, w])
}

/// Sizes `(B, T, C_in, C_out, H, W)` and the dilations they run with: T from 4 (where 9 wraps
/// to 1) to 256, one-row and one-column frames, a frame of several bands, and one wide enough
/// for the direct loops (the others run the im2col GEMM).
const CASES: [((usize, usize, usize, usize, usize, usize), usize); 9] = [
    ((2, 4, 1, 3, 5, 6), 1),
    ((1, 4, 2, 2, 3, 4), 9),
    ((1, 8, 3, 2, 1, 7), 3),
    ((2, 16, 4, 4, 6, 5), 9),
    ((1, 32, 4, 1, 4, 1), 3),
    ((1, 13, 2, 3, 9, 8), 9),
    ((1, 256, 1, 4, 4, 4), 9),
    ((1, 6, 8, 8, 40, 60), 3),
    // wide enough for the direct loops
    ((1, 12, 4, 4, 5, 150), 9),
];

#[test]
fn the_kernel_equals_roll_and_concatenate_in_values_and_gradients() {
    for &((b, t, ci, co, h, w), d) in &CASES {
        let case = (b, t, ci, co, h, w, d);
        let device = Device::flex().autodiff();
        let x = Tensor::<5>::random([b, t, ci, h, w], Distribution::Normal(0.0, 1.0), &device).require_grad();
        let k = Tensor::<4>::random([co, 3 * ci, 3, 3], Distribution::Normal(0.0, 0.3), &device).require_grad();
        let bias = Tensor::<1>::random([co], Distribution::Normal(0.0, 1.0), &device).require_grad();
        // a loss that weights every output element differently
        let wts = Tensor::<5>::random([b, t, co, h, w], Distribution::Normal(0.0, 1.0), &device);

        let ours = delay_conv3x3(x.clone(), k.clone(), bias.clone(), d);
        let theirs = reference(x.clone(), k.clone(), bias.clone(), d);
        let s = scale(&theirs);
        let e = max_abs_diff(ours.clone(), theirs.clone());
        assert!(e <= 1e-5 * s, "{case:?}: forward differs by {e} (scale {s})");

        let g_ours = (ours * wts.clone()).sum().backward();
        let g_theirs = (theirs * wts).sum().backward();
        let (a, r) = (x.grad(&g_ours).unwrap(), x.grad(&g_theirs).unwrap());
        let e = max_abs_diff(a, r.clone());
        assert!(e <= 1e-4 * scale(&r), "{case:?}: dx differs by {e} (scale {})", scale(&r));
        let (a, r) = (k.grad(&g_ours).unwrap(), k.grad(&g_theirs).unwrap());
        let e = max_abs_diff(a, r.clone());
        assert!(e <= 1e-4 * scale(&r), "{case:?}: dkernel differs by {e} (scale {})", scale(&r));
        let (a, r) = (bias.grad(&g_ours).unwrap(), bias.grad(&g_theirs).unwrap());
        let e = max_abs_diff(a, r.clone());
        assert!(e <= 1e-4 * scale(&r), "{case:?}: dbias differs by {e}");

        // without autodiff, and the composed form the GPU runs
        let plain = Device::flex();
        let x = Tensor::<5>::random([b, t, ci, h, w], Distribution::Normal(0.0, 1.0), &plain);
        let k = Tensor::<4>::random([co, 3 * ci, 3, 3], Distribution::Normal(0.0, 0.3), &plain);
        let bias = Tensor::<1>::random([co], Distribution::Normal(0.0, 1.0), &plain);
        let theirs = reference(x.clone(), k.clone(), bias.clone(), d);
        let e = max_abs_diff(delay_conv3x3(x.clone(), k.clone(), bias.clone(), d), theirs.clone());
        assert!(e <= 1e-5 * scale(&theirs), "{case:?}: inference forward differs by {e}");
        let e = max_abs_diff(delay_conv3x3_composed(x, k, bias, d), theirs.clone());
        assert!(e <= 1e-5 * scale(&theirs), "{case:?}: composed forward differs by {e}");
    }
}

/// Delaying the input by whole bins delays the output the same (the reason for the op), and a
/// strided (permuted) input is read through its strides.
#[test]
fn the_op_commutes_with_delays_and_reads_strided_inputs() {
    let device = Device::flex();
    let (b, t, ci, co, h, w) = (2, 12, 2, 3, 5, 4);
    let x = Tensor::<5>::random([b, t, ci, h, w], Distribution::Normal(0.0, 1.0), &device);
    let k = Tensor::<4>::random([co, 3 * ci, 3, 3], Distribution::Normal(0.0, 0.3), &device);
    let bias = Tensor::<1>::random([co], Distribution::Normal(0.0, 1.0), &device);
    for d in [1, 3, 9] {
        let base = delay_conv3x3(x.clone(), k.clone(), bias.clone(), d);
        for s in [1i64, 5, -4] {
            let shifted = delay_conv3x3(x.clone().roll_dim(s, 1), k.clone(), bias.clone(), d);
            let e = max_abs_diff(shifted, base.clone().roll_dim(s, 1));
            assert!(e <= 1e-5 * scale(&base), "d = {d}, shift {s}: {e}");
        }
    }
    let strided = Tensor::<5>::random([b, t, ci, w, h], Distribution::Normal(0.0, 1.0), &device).swap_dims(3, 4); // [B, T, C, H, W], not contiguous
    let contiguous = Tensor::<5>::from_data(strided.clone().into_data(), &device);
    let e = max_abs_diff(delay_conv3x3(strided, k.clone(), bias.clone(), 3), delay_conv3x3(contiguous, k, bias, 3));
    assert_eq!(e, 0.0, "a strided input gives the same bytes as its contiguous copy");
}
