//! The range fit's evidence in tensor operations, differentiable in the sensor's matrix `A` and
//! in the taps: what lets deep sensing learn codes for the U-Net on the range fit's evidence
//! ([`crate::UnetInput::Costs`]) on the range error itself.
//!
//! As for the lifetime fit ([`crate::lifetime_evidence`]): the fit
//! ([`tcsense_fits::depth::RangeTemplates`]) runs on the CPU from the hard codes and gives the
//! values; this copy gives the gradient, through the straight-through estimator
//! (`e = e_fit + (e_copy − stop(e_copy))`). It equals the fit in value up to f32 rounding
//! (tested). The branch of each non-negative least-squares solve (both columns, or the better
//! one alone) is chosen by the values and held within a step, as the frame's noise level is.
//!
//! For a pixel of subpixel type `n` with taps `y` (lit where `Σ y > 0`):
//!
//! ```text
//! g_c = A_n P_c    candidate c's pulse (P_c: two neighbouring columns, linear; the fit's grid)
//! s   = A_n 1      the ambient's column
//! a, b = argmin_{a, b ≥ 0} ‖y − a g_c − b s‖²,   c_c = that least square      (the pixel's cost)
//! L_w = −(C_w − min C_w)·ν     C_w: c summed over the fit's window and over the wider ones
//! posteriors: softmax(−c·ν) and softmax(−C_w·ν) of the wider windows, pooled
//! ```

use burn::tensor::{Tensor, TensorData};
use tcsense_fits::depth::{candidate_columns, CONTEXT_WINDOWS};

use crate::evidence_tensors::{log_likelihood, pooled_posterior, type_onehot, window_sum};

/// The evidence of a batch of frames as the fit computes it (see the module's notes).
///
/// # Shapes
/// - `y`: `[B, M, H, W]`, `a`: `A` per subpixel type `[1, N, M, T]`, `nats`: `ν` per frame `[B]`
///   → pooled posteriors `[B, S·⌈C/pool⌉, H, W]`, skip `[B, S·C, H, W]` (`S` = 1 + the wider
///   windows, `C = T·oversample`)
pub fn range_evidence(
    y: Tensor<4>,
    a: Tensor<4>,
    block: (usize, usize),
    oversample: usize,
    nats: Tensor<1>,
    window: usize,
    pool: usize,
) -> (Tensor<4>, Tensor<4>) {
    let [b, m, h, w] = y.dims();
    let [_, n, _, t] = a.dims();
    let hw = h * w;
    let device = y.device();
    // the candidates' templates [N, M, C] and the ambient's column [N, M]
    let cols = candidate_columns(t, oversample);
    let c = cols.len();
    let mut p = vec![0f32; t * c];
    for (k, &(t0, t1, f)) in cols.iter().enumerate() {
        p[t0 * c + k] += (1.0 - f) as f32;
        p[t1 * c + k] += f as f32;
    }
    let p = Tensor::<2>::from_data(TensorData::new(p, [t, c]), &device);
    let a3 = a.reshape([n * m, t]);
    let g = a3.clone().matmul(p).reshape([n, m, c]);
    let s = a3.sum_dim(1).reshape([n, m, 1]);
    // onto the pixels
    let onehot = type_onehot(n, (h, w), block, &device);
    let per_pixel = |v: Tensor<3>, k: usize| v.reshape([n, m * k]).swap_dims(0, 1).matmul(onehot.clone()).reshape([1, m, k, hw]);
    let g = per_pixel(g, c); // [1, M, C, HW]
    let s = per_pixel(s, 1); // [1, M, 1, HW]
    let yv = y.clone().reshape([b, m, 1, hw]);
    let dot = |u: Tensor<4>, v: Tensor<4>| (u * v).sum_dim(1); // over the taps → [·, 1, ·, HW]
    let (yy, gy, sy) = (dot(yv.clone(), yv.clone()), dot(g.clone(), yv.clone()), dot(s.clone(), yv));
    let (gg, gs, ss) = (dot(g.clone(), g.clone()), dot(g, s.clone()), dot(s.clone(), s));
    // the two columns together where the solve is posed and both amplitudes are ≥ 0 …
    let det = gg.clone() * ss.clone() - gs.clone() * gs.clone();
    let posed = det.clone().greater(gg.clone() * ss.clone() * 1e-12).float().detach();
    let inv_det = posed.clone() / det.clamp_min(1e-30);
    let amp_g = (ss.clone() * gy.clone() - gs.clone() * sy.clone()) * inv_det.clone();
    let amp_s = (gg.clone() * sy.clone() - gs * gy.clone()) * inv_det;
    let inside = yy.clone() - amp_g.clone() * gy.clone() - amp_s.clone() * sy.clone();
    let both = (amp_g.greater_equal_elem(0.0).float() * amp_s.greater_equal_elem(0.0).float()).detach() * posed;
    // … else the better column alone
    let only_g = gy.clamp_min(0.0).powi_scalar(2) * gg.clone().greater_elem(0.0).float().detach() / gg.clamp_min(1e-30);
    let only_s = sy.clamp_min(0.0).powi_scalar(2) * ss.clone().greater_elem(0.0).float().detach() / ss.clamp_min(1e-30);
    let boundary = yy - only_g.max_pair(only_s);
    let cost = (inside * both.clone() + boundary * (both.ones_like() - both)).clamp_min(0.0); // [B, 1, C, HW]
    let lit = y.sum_dim(1).greater_elem(0.0).float().detach(); // [B, 1, H, W]
    let pixel = cost.reshape([b, c, h, w]) * lit.clone();
    // the fit's window and the wider ones
    let windows: Vec<Tensor<4>> = std::iter::once(window).chain(CONTEXT_WINDOWS).map(|side| window_sum(pixel.clone(), side)).collect();
    let nats = nats.reshape([b, 1, 1, 1]);
    let skip: Vec<Tensor<4>> = windows.iter().map(|v| log_likelihood(v.clone(), nats.clone(), lit.clone())).collect();
    // the posteriors of the pixel and of the wider windows, pooled
    let posts: Vec<Tensor<4>> =
        std::iter::once(pixel).chain(windows.into_iter().skip(1)).map(|v| pooled_posterior(v, nats.clone(), lit.clone(), pool)).collect();
    (Tensor::cat(posts, 1), Tensor::cat(skip, 1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evidence_tensors::testing::{assert_the_gradient_is_the_derivative, noisy_with_a_dark_pixel};
    use crate::net::Network;
    use crate::sensor_tensors::SensorTensors;
    use crate::{Unet, UnetConfig, UnetHead, UnetInput};
    use burn::tensor::Device;
    use tcsense_sensor::{Codes, Irf, MeasurementMatrix, SensorParams};

    /// A noisy 16×16 frame through the zoo's range codes (physical IRF, oversampling 2): a slope
    /// from 3 to 25 bins on ambient, one pixel dark; its sensor and an untrained network.
    fn frame(device: &Device) -> (MeasurementMatrix, Vec<f32>, (usize, usize), Unet) {
        let codes = Codes::from_json(include_str!("../../zoo/unet-lidar-designed/codes.json")).unwrap();
        let params = SensorParams {
            irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            sampling: tcsense_sensor::Sampling::Oversample(2),
            ..SensorParams::from_codes(&codes)
        };
        let a = MeasurementMatrix::synthesize(&codes, &params.validate().unwrap()).unwrap();
        let (h, w, t) = (16, 16, a.bins());
        let mut x = vec![3f32; t * h * w];
        for p in 0..h * w {
            let tau = 3.0 + 22.0 * (p % w) as f64 / (w - 1) as f64 + 0.3 * (p / w) as f64;
            let q = tau - 0.5;
            let t0 = q.floor() as usize;
            x[(t0 % t) * h * w + p] += (400.0 * (1.0 - (q - q.floor()))) as f32;
            x[((t0 + 1) % t) * h * w + p] += (400.0 * (q - q.floor())) as f32;
        }
        let st = SensorTensors::new(&a, h, w, device).unwrap();
        let y: Vec<f32> = st.forward(Tensor::<4>::from_data(TensorData::new(x, [1, t, h, w]), device)).into_data().try_into_vec().unwrap();
        let y = noisy_with_a_dark_pixel(y, h * w, 37);
        let range = tcsense_sensor::C * a.bin_width_s() / 2.0 * t as f64;
        let net = UnetConfig::new(4, t, range)
            .with_base_width(4)
            .with_levels(2)
            .with_head(UnetHead::ScoreVolume)
            .with_input(UnetInput::Costs)
            .with_oversample(2)
            .init(device);
        (a, y, (h, w), net)
    }

    /// The tensor copy gives the fit's evidence: every window's log-likelihoods and every
    /// posterior, the dark pixel's included.
    #[test]
    fn the_copy_equals_the_fit_in_value() {
        let device = Device::flex();
        let (a, y, (h, w), net) = frame(&device);
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let yt = Tensor::<4>::from_data(TensorData::new(y.clone(), [1, 4, h, w]), &device);
        let (features, skip, noise) = net.evidence_frames(yt.clone(), &st);
        let (c, pool) = net.grid();
        let nats = Tensor::<1>::from_data(TensorData::new(vec![1.0 / (2.0 * noise[0])], [1]), &device);
        let (post, copy) = range_evidence(yt, st.a.clone(), st.block, 2, nats, net.fit_options().fit.window, pool);
        let s = 1 + CONTEXT_WINDOWS.len();
        assert_eq!((copy.dims(), post.dims()[1]), ([1, s * c, h, w], s * c.div_ceil(pool)));
        let v = |x: Tensor<4>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
        let (fit_skip, copy_skip) = (v(skip), v(copy));
        let scale = fit_skip.iter().fold(0f32, |m, x| m.max(x.abs()));
        assert!(scale > 10.0, "the frame discriminates ranges: {scale} nats");
        let worst = fit_skip.iter().zip(&copy_skip).map(|(f, c)| (f - c).abs()).fold(0f32, f32::max);
        assert!(worst <= 1e-3 * scale, "skip: {worst} nats apart of {scale}");
        let fit_post = v(features.narrow(1, 0, post.dims()[1]));
        let worst = fit_post.iter().zip(&v(post)).map(|(f, c)| (f - c).abs()).fold(0f32, f32::max);
        assert!(worst <= 2e-3 * pool as f32, "posteriors: {worst} apart");
        assert!(fit_post.iter().skip(37).step_by(h * w).all(|&v| v == 0.0), "the dark pixel has no posterior");
    }

    /// Deep sensing's path: on a learnable `A` the training output keeps the fit's values and
    /// has a gradient in `A` that equals central differences of the copy.
    #[test]
    fn the_training_output_reaches_the_codes_with_the_derivative() {
        let device = Device::flex().autodiff();
        let (a, y, (h, w), net) = frame(&device);
        let t = a.bins();
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let a_t = st.a.clone().reshape([4, 4, t]).require_grad();
        let learnable = st.clone().with_matrix(a_t.clone());
        let yt = || Tensor::<4>::from_data(TensorData::new(y.clone(), [1, 4, h, w]), &device);
        let v = |x: Tensor<4>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
        let fixed = net.train_output(yt(), &st);
        let out = net.train_output(yt(), &learnable);
        assert_eq!(v(fixed.clone()), v(out.clone()), "the same values");
        let k = 2 * net.returns();
        let g: Vec<f32> = a_t.grad(&out.narrow(1, k, 8).sum().backward()).expect("a gradient in A").into_data().try_into_vec().unwrap();
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| v.abs() > 0.0), "the log-posterior moves with A");
        // the copy's gradient is its derivative
        let (_, _, noise) = net.evidence_frames(yt(), &st);
        let (c, pool) = net.grid();
        let wk: Vec<f32> = (0..4 * c * h * w).map(|i| ((i * 40503) % 17) as f32 / 17.0).collect();
        let nats = Tensor::<1>::from_data(TensorData::new(vec![1.0 / (2.0 * noise[0])], [1]), &device);
        assert_the_gradient_is_the_derivative(&st.a, 1e-4, |a_t| {
            let (post, skip) = range_evidence(yt(), a_t, st.block, 2, nats.clone(), 3, pool);
            let wt = Tensor::<4>::from_data(TensorData::new(wk.clone(), [1, 4 * c, h, w]), &device);
            let pc = post.dims()[1];
            (skip * wt.clone()).sum() + (post * wt.narrow(1, 0, pc)).sum().mul_scalar(10.0)
        });
    }
}
