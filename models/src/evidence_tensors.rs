//! The steps of the fits' evidence ([`tcsense_fits::evidence`]) in tensor operations, shared by
//! the differentiable copies of the lifetime fit ([`crate::lifetime_evidence`]) and of the
//! range fit ([`crate::range_evidence`]): the window's sum, the log-likelihood of every
//! candidate and the pooled per-pixel posterior, on costs `[B, C, H, W]` (`C` candidates).

use burn::tensor::activation::softmax;
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;
use burn::tensor::{Device, Tensor, TensorData};
use tcsense_sensor::waveform::subpixel_flat;

/// Each pixel's subpixel type as a one-hot `[N, H·W]`: `v [·, N] × onehot` gives every pixel its
/// type's row.
pub(crate) fn type_onehot(n: usize, (h, w): (usize, usize), block: (usize, usize), device: &Device) -> Tensor<2> {
    let hw = h * w;
    let mut onehot = vec![0f32; n * hw];
    for p in 0..hw {
        onehot[subpixel_flat(p, w, block) * hw + p] = 1.0;
    }
    Tensor::<2>::from_data(TensorData::new(onehot, [n, hw]), device)
}

/// Costs summed over the `side × side` window around every pixel, zero outside the frame (the
/// fits' box filter).
///
/// # Shapes
/// - `cost`: `[B, C, H, W]` → `[B, C, H, W]`
pub(crate) fn window_sum(cost: Tensor<4>, side: usize) -> Tensor<4> {
    let opts = AvgPoolOptions::new([side, side]).with_stride([1, 1]).with_padding([side / 2, side / 2]).with_count_include_pad(true);
    avg_pool2d(cost, opts).mul_scalar((side * side) as f32)
}

/// The log-likelihood of every candidate, `−(C − min_c C)·ν`, where the pixel is lit.
///
/// # Shapes
/// - `cost`: `[B, C, H, W]`, `nats`: `ν` `[B, 1, 1, 1]`, `lit`: `[B, 1, H, W]` → `[B, C, H, W]`
pub(crate) fn log_likelihood(cost: Tensor<4>, nats: Tensor<4>, lit: Tensor<4>) -> Tensor<4> {
    (cost.clone().min_dim(1) - cost) * nats * lit
}

/// The posterior `softmax_c(−C·ν)` summed over groups of `pool` candidates and scaled by their
/// count `⌈C/pool⌉` (a flat posterior is 1 in every channel), where the pixel is lit.
///
/// # Shapes
/// - `cost`: `[B, C, H, W]`, `nats`: `[B, 1, 1, 1]`, `lit`: `[B, 1, H, W]` → `[B, ⌈C/pool⌉, H, W]`
pub(crate) fn pooled_posterior(cost: Tensor<4>, nats: Tensor<4>, lit: Tensor<4>, pool: usize) -> Tensor<4> {
    let [b, c, h, w] = cost.dims();
    let pool = pool.max(1);
    let pooled = c.div_ceil(pool);
    let q = softmax((cost.clone().min_dim(1) - cost) * nats, 1);
    let q = if pooled * pool > c { Tensor::cat(vec![q, Tensor::zeros([b, pooled * pool - c, h, w], &lit.device())], 1) } else { q };
    q.reshape([b, pooled, pool, h, w]).sum_dim(2).reshape([b, pooled, h, w]).mul_scalar(pooled as f32) * lit
}

/// The fit's evidence carrying the gradient of its copy (the straight-through estimator): the
/// values are the fit's to the bit (`x − stop(x)` is exactly 0); the copy's pooled posteriors
/// take the place of the features' first channels (the log intensity and the lit mask after
/// them carry no gradient).
///
/// # Shapes
/// - `features`: `[B, F, H, W]`, `skip`: `[B, S, H, W]`, `post`: `[B, F − 2, H, W]`, `copy`:
///   `[B, S, H, W]` → features, skip
pub(crate) fn with_gradient_of(features: Tensor<4>, skip: Tensor<4>, post: Tensor<4>, copy: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
    let [b, _, h, w] = post.dims();
    let post = Tensor::cat(vec![post.clone(), Tensor::zeros([b, 2, h, w], &post.device())], 1);
    (features + (post.clone() - post.detach()), skip + (copy.clone() - copy.detach()))
}

/// The fit's window's log-likelihood plus the `wide` wider windows' at the weights the head sets
/// pixel by pixel, `L_0 + Σ_s e^{clip(6·o_s − 6)}·L_s` (the networks on a fit's evidence): the
/// log-weights `o_s` are the head's channels after its `points` log-prior channels and its
/// confidence logit.
///
/// # Shapes
/// - `o`: `[B, G + 1 + S, H, W]`, `skip`: `[B, (1 + S)·G, H, W]` (window-major) → `[B, G, H, W]`
pub(crate) fn windowed_likelihood(o: &Tensor<4>, skip: Tensor<4>, points: usize, wide: usize) -> Tensor<4> {
    use crate::depth_evidence::{TEMPERATURE_RANGE, WIDER_GAIN, WIDER_OFFSET};
    let [b, _, h, w] = o.dims();
    let weights = o
        .clone()
        .narrow(1, points + 1, wide)
        .mul_scalar(WIDER_GAIN)
        .add_scalar(WIDER_OFFSET)
        .clamp(TEMPERATURE_RANGE[0], TEMPERATURE_RANGE[1])
        .exp(); // [B, S, H, W]
    let wider = skip.clone().narrow(1, points, wide * points).reshape([b, wide, points, h, w]) * weights.reshape([b, wide, 1, h, w]);
    skip.narrow(1, 0, points) + wider.sum_dim(1).reshape([b, points, h, w])
}

#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use tcsense_sensor::MeasurementMatrix;

    /// The prototype codes (4 taps, 2×2, L = 32) at heterodyne 4 through the physical IRF: a FLIm
    /// sensor of 128 bins.
    pub(crate) fn prototype_flim_matrix() -> MeasurementMatrix {
        let codes = tcsense_sensor::generate::prototype_codes(1).expect("the prototype codes");
        let spec = tcsense_sensor::SensorParams {
            sampling: tcsense_sensor::Sampling::Heterodyne(4),
            irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            ..tcsense_sensor::SensorParams::from_codes(&codes)
        }
        .validate()
        .expect("a valid FLIm sensor");
        MeasurementMatrix::synthesize(&codes, &spec).expect("its matrix")
    }

    /// Clean taps `[M, H·W]` made noisy by a deterministic pattern of about `√y` (shot noise),
    /// with pixel `dark` holding no charge.
    pub(crate) fn noisy_with_a_dark_pixel(y: Vec<f32>, hw: usize, dark: usize) -> Vec<f32> {
        let mut y: Vec<f32> = y.iter().enumerate().map(|(i, v)| v + v.sqrt() * (((i * 7919) % 13) as f32 / 6.0 - 1.0)).collect();
        for m in 0..y.len() / hw {
            y[m * hw + dark] = 0.0;
        }
        y
    }

    /// Autodiff's derivative of `loss` at `a` along a fixed direction against central differences
    /// with a step of `rel` of the largest entry of `a`: within 5 %, and not zero.
    pub(crate) fn assert_the_gradient_is_the_derivative(a: &Tensor<4>, rel: f32, loss: impl Fn(Tensor<4>) -> Tensor<1>) {
        let device = a.device();
        let av: Vec<f32> = a.clone().into_data().try_into_vec().expect("f32 entries");
        let dir: Vec<f32> = (0..av.len()).map(|i| ((i * 2654435761usize) % 1000) as f32 / 1000.0 - 0.5).collect();
        let at = |v: Vec<f32>| Tensor::<4>::from_data(TensorData::new(v, a.dims()), &device);
        let a_t = at(av.clone()).require_grad();
        let grad: Vec<f32> =
            a_t.grad(&loss(a_t.clone()).backward()).expect("a gradient in A").into_data().try_into_vec().expect("f32 entries");
        let analytic: f64 = grad.iter().zip(&dir).map(|(g, d)| (*g as f64) * (*d as f64)).sum();
        let step = av.iter().fold(0f32, |m, v| m.max(v.abs())) * rel;
        let moved = |s: f32| -> f64 {
            let v: Vec<f32> = av.iter().zip(&dir).map(|(a, d)| a + s * step * d).collect();
            loss(at(v)).into_scalar::<f32>() as f64
        };
        let numeric = (moved(1.0) - moved(-1.0)) / (2.0 * step as f64);
        assert!(analytic.abs() > 1e-3, "a gradient: {analytic}");
        assert!((analytic - numeric).abs() <= 0.05 * numeric.abs(), "autodiff {analytic}, central differences {numeric}");
    }
}
