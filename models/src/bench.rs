//! Timings of the custom kernels against what burn-flex does without them, for
//! `tcsense bench kernels` (printed, never asserted).

use burn::backend::flex::{Flex, FlexDevice, FlexTensor};
use burn::backend::ops::{ConvOptions, FloatTensorOps, ModuleOps};
use burn::tensor::{Distribution, Shape, Tensor, TensorData};
use tcsense_sensor::MeasurementMatrix;

use tcsense_kernels::conv_op::Conv3x3Backend;
use tcsense_kernels::timing;

use crate::{Device, SensorTensors};

/// One operation: our kernel and burn-flex's generic path, median milliseconds.
#[derive(Debug, Clone, PartialEq)]
pub struct OpTiming {
    /// What was timed.
    pub name: String,
    /// Our kernel.
    pub ours_ms: f64,
    /// burn-flex (generic conv2d, or the DC composed from burn ops in block layout).
    pub burn_ms: f64,
    /// Floating-point operations of one call (0 where not meaningful).
    pub flop: f64,
}

/// Median milliseconds of an infallible call (warm-up included).
fn median_ms(mut f: impl FnMut(), reps: usize) -> f64 {
    timing::median_ms::<std::convert::Infallible>(
        || {
            f();
            Ok(())
        },
        reps,
    )
    .unwrap_or(f64::NAN)
}

/// Deterministic values in [−1, 1) (a linear congruential sequence).
fn random(shape: [usize; 4], seed: u64) -> FlexTensor {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let v: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
        })
        .collect();
    Flex::float_from_data(TensorData::new(v, Shape::from(shape)), &FlexDevice)
}

/// Time one 3×3 conv layer `C → C` on `[B, C, H, W]` (forward, input gradient, weight gradient)
/// and the data-consistency step on `[B, T, H, W]` with the sensor `a`.
pub fn bench_kernels(
    a: &MeasurementMatrix,
    batch: usize,
    channels: usize,
    h: usize,
    w: usize,
    reps: usize,
) -> crate::Result<Vec<OpTiming>> {
    let (b, c) = (batch, channels);
    let x = random([b, c, h, w], 1);
    let g = random([b, c, h, w], 2);
    let k = random([c, c, 3, 3], 3);
    let bias = Flex::float_from_data(TensorData::new(vec![0.1f32; c], Shape::from([c])), &FlexDevice);
    let opts = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let flop = 2.0 * (b * c * c * 9 * h * w) as f64;
    let mut out = vec![
        OpTiming {
            name: "conv 3x3 forward".into(),
            ours_ms: median_ms(|| drop(Flex::conv3x3(x.clone(), k.clone(), bias.clone())), reps),
            burn_ms: median_ms(|| drop(Flex::conv2d(x.clone(), k.clone(), Some(bias.clone()), opts.clone())), reps),
            flop,
        },
        OpTiming {
            name: "conv 3x3 input grad".into(),
            ours_ms: median_ms(|| drop(Flex::conv3x3_x_backward(g.clone(), k.clone())), reps),
            burn_ms: median_ms(|| drop(Flex::conv2d_x_backward(x.clone(), k.clone(), g.clone(), opts.clone())), reps),
            flop,
        },
        OpTiming {
            name: "conv 3x3 weight grad".into(),
            ours_ms: median_ms(|| drop(Flex::conv3x3_w_backward(x.clone(), g.clone())), reps),
            burn_ms: median_ms(|| drop(Flex::conv2d_weight_backward(x.clone(), k.clone(), g.clone(), opts.clone())), reps),
            flop,
        },
    ];
    let device = Device::flex();
    let s = SensorTensors::new(a, h, w, &device)?;
    let t = a.bins();
    let v = Tensor::<4>::random([b, t, h, w], Distribution::Uniform(0.0, 1.0), &device);
    let rho = Tensor::<1>::from_floats([0.1], &device);
    let y = Tensor::<4>::random([b, a.taps(), h, w], Distribution::Uniform(0.0, 1.0), &device);
    let sync = |t: Tensor<4>| drop(t.into_data());
    out.push(OpTiming {
        name: "data consistency".into(),
        ours_ms: median_ms(|| sync(s.data_consistency(v.clone(), rho.clone())), reps),
        burn_ms: median_ms(|| sync(s.from_blocks(s.data_consistency_blocks(s.to_blocks(v.clone()), rho.clone()))), reps),
        flop: 0.0,
    });
    out.push(OpTiming {
        name: "back-projection".into(),
        ours_ms: median_ms(|| sync(s.pinv(y.clone())), reps),
        burn_ms: median_ms(|| sync(s.pinv_blocks(y.clone())), reps),
        flop: 0.0,
    });
    Ok(out)
}

/// The U-Net's operations besides its 3×3 convs — 2×2 max-pooling and nearest up-sampling by
/// 2, ours against burn-flex's generic paths (`max_pool2d`; reshape + `repeat_dim`), forward
/// and forward + backward — and the whole U-Net forward pass, at an `h × w` frame (batch 1,
/// the default widths).
pub fn bench_unet_ops(a: &MeasurementMatrix, h: usize, w: usize, reps: usize) -> crate::Result<(Vec<OpTiming>, f64)> {
    use crate::unet::UnetConfig;
    use burn::tensor::module::max_pool2d;
    use burn::tensor::ops::MaxPoolOptions;
    use tcsense_kernels::resample::{max_pool2, upsample2};
    let repeat_up = |x: Tensor<4>| {
        let [b, c, h, w] = x.dims();
        x.reshape([b, c, h, 1, w, 1]).repeat_dim(3, 2).repeat_dim(5, 2).reshape([b, c, 2 * h, 2 * w])
    };
    let device = Device::flex();
    let cfg = UnetConfig::new(a.taps(), a.bins(), 10.0);
    let (c0, c1) = (cfg.width(0), cfg.width(1));
    let level0 = Tensor::<4>::random([1, c0, h, w], Distribution::Uniform(0.0, 1.0), &device);
    let level1 = Tensor::<4>::random([1, c1, h / 2, w / 2], Distribution::Uniform(0.0, 1.0), &device);
    let sync = |t: Tensor<4>| drop(t.into_data());
    let ad = device.clone().autodiff();
    let x0 = Tensor::<4>::random([1, c0, h, w], Distribution::Uniform(0.0, 1.0), &ad).require_grad();
    let x1 = Tensor::<4>::random([1, c1, h / 2, w / 2], Distribution::Uniform(0.0, 1.0), &ad).require_grad();
    let timings = vec![
        OpTiming {
            name: format!("max-pool 2x2 [1,{c0},{h},{w}]"),
            ours_ms: median_ms(|| sync(max_pool2(level0.clone())), reps),
            burn_ms: median_ms(|| sync(max_pool2d(level0.clone(), MaxPoolOptions::new([2, 2]))), reps),
            flop: 0.0,
        },
        OpTiming {
            name: "max-pool fwd+bwd".into(),
            ours_ms: median_ms(|| drop(max_pool2(x0.clone()).sum().backward()), reps),
            burn_ms: median_ms(|| drop(max_pool2d(x0.clone(), MaxPoolOptions::new([2, 2])).sum().backward()), reps),
            flop: 0.0,
        },
        OpTiming {
            name: format!("up-sample x2 [1,{c1},{},{}]", h / 2, w / 2),
            ours_ms: median_ms(|| sync(upsample2(level1.clone())), reps),
            burn_ms: median_ms(|| sync(repeat_up(level1.clone())), reps),
            flop: 0.0,
        },
        OpTiming {
            name: "up-sample fwd+bwd".into(),
            ours_ms: median_ms(|| drop(upsample2(x1.clone()).sum().backward()), reps),
            burn_ms: median_ms(|| drop(repeat_up(x1.clone()).sum().backward()), reps),
            flop: 0.0,
        },
    ];
    let net = cfg.init(&device);
    let s = SensorTensors::new(a, h, w, &device)?;
    let y = Tensor::<4>::random([1, a.taps(), h, w], Distribution::Uniform(0.0, 1.0), &device);
    let whole = median_ms(|| sync(net.logits(y.clone(), &s)), reps);
    Ok((timings, whole))
}
