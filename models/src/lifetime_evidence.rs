//! The lifetime fit's evidence in tensor operations, differentiable in the sensor's matrix `A`
//! and in the taps: what lets deep sensing learn codes for the evidence network
//! ([`crate::lifetime::LifetimeInput::Costs`]) on the lifetime error itself.
//!
//! The fit ([`tcsense_fits::lifetime_taps`]) runs on the CPU from the hard codes and gives no
//! gradient: it searches the instrument (onset and IRF width) over discrete candidates, then
//! costs every lifetime of its grid. During deep sensing the network reads the fit's evidence
//! in value, and the gradient comes from this copy at the instrument the fit found, through
//! the straight-through estimator the measurements use too (`e = e_fit + e_copy − stop(e_copy)`).
//! The copy equals the fit in value up to f32 rounding (tested), so the gradient is the fit's
//! own, except for the instrument's dependence on the codes, held fixed within a step.
//!
//! For a pixel of subpixel type `n` with taps `y` and charge `s = Σ_m y_m` (lit where `s > 0`):
//!
//! ```text
//! g_i = A_n d_i / Σ_m (A_n d_i)_m     template of lifetime i (d_i: the decay at the instrument, [T])
//! b   = A_n 1 / Σ_m (A_n 1)_m         the background's template
//! r   = y / s
//! β_i = clamp(⟨r − g_i, b − g_i⟩ / ‖b − g_i‖², 0, 1)
//! c_i = s · ‖r − g_i − β_i (b − g_i)‖²          the pixel's cost; C_i: summed over the window
//! skip_i     = −(C_i − min_j C_j) · ν             ν = 1 / (2 · the frame's noise level)
//! posterior  = (G/pool) · Σ_pool softmax_i(−c_i · ν)
//! ```

use burn::tensor::{Device, Tensor, TensorData};
use tcsense_fits::lifetime_taps::{grid_decays, Instrument, TapFitOptions};
use tcsense_sensor::MeasurementMatrix;

use crate::evidence_tensors::{log_likelihood, pooled_posterior, type_onehot, window_sum};

/// Least denominator of the normalisations (a template of no charge).
const FLOOR: f32 = 1e-30;

/// The decays of `opts`' grid at each frame's instrument ([`grid_decays`]), as
/// [`lifetime_evidence`] reads them.
///
/// # Shapes
/// - `instruments`: one per frame `[B]` → `[B, T, G]`
pub fn decays_tensor(a: &MeasurementMatrix, instruments: &[Instrument], opts: &TapFitOptions, device: &Device) -> Tensor<3> {
    let (b, t, g) = (instruments.len(), a.bins(), opts.points);
    let mut decays = vec![0f32; b * t * g];
    for (i, instrument) in instruments.iter().enumerate() {
        for (k, curve) in grid_decays(a, *instrument, opts).iter().enumerate() {
            for (j, v) in curve.iter().enumerate() {
                decays[(i * t + j) * g + k] = *v as f32;
            }
        }
    }
    Tensor::<3>::from_data(TensorData::new(decays, [b, t, g]), device)
}

/// The evidence of a batch of frames as the fit computes it (see the module's notes), from the
/// decays of each frame's instrument.
///
/// # Shapes
/// - `y`: `[B, M, H, W]`, `a`: `A` per subpixel type `[1, N, M, T]`, `decays`: each frame's
///   curves of the grid's lifetimes `[B, T, G]` ([`decays_tensor`]), `nats`: `ν` per frame
///   `[B]` → pooled posteriors `[B, ⌈G/pool⌉, H, W]`, skip `[B, G, H, W]`
#[allow(clippy::too_many_arguments)]
pub fn lifetime_evidence(
    y: Tensor<4>,
    a: Tensor<4>,
    block: (usize, usize),
    decays: Tensor<3>,
    nats: Tensor<1>,
    window: usize,
    pool: usize,
    background: bool,
) -> (Tensor<4>, Tensor<4>) {
    let [b, m, h, w] = y.dims();
    let [_, n, _, t] = a.dims();
    let g = decays.dims()[2];
    let hw = h * w;
    // the templates of every type, normalised over the taps
    let proj = a.clone().reshape([1, n * m, t]).expand([b, n * m, t]).matmul(decays).reshape([b, n, m, g]);
    let tpl = proj.clone() / proj.sum_dim(2).clamp_min(FLOOR); // [B, N, M, G]
    let bg = a.sum_dim(3).reshape([1, n, m]);
    let bg = bg.clone() / bg.sum_dim(2).clamp_min(FLOOR); // [1, N, M]
                                                          // onto the pixels: each pixel takes its type's row
    let onehot = type_onehot(n, (h, w), block, &y.device());
    let tpl = tpl.reshape([b, n, m * g]).swap_dims(1, 2).matmul(onehot.clone().unsqueeze::<3>().expand([b, n, hw])).reshape([b, m, g, hw]);
    let bg = bg.swap_dims(1, 2).matmul(onehot.unsqueeze::<3>()).reshape([1, m, 1, hw]);
    // the taps over their sum
    let s = y.clone().sum_dim(1); // [B, 1, H, W]
    let lit = s.clone().greater_elem(0.0).float().detach(); // [B, 1, H, W]
    let r = (y / s.clone().clamp_min(FLOOR)).reshape([b, m, 1, hw]);
    let d = bg - tpl.clone(); // [B, M, G, HW]
    let e = r - tpl;
    let e = if background {
        let beta = (e.clone() * d.clone()).sum_dim(1) / (d.clone() * d.clone()).sum_dim(1).clamp_min(FLOOR);
        e - beta.clamp(0.0, 1.0) * d
    } else {
        e
    };
    let weight = (s * lit.clone()).reshape([b, 1, 1, hw]);
    let pixel = ((e.clone() * e).sum_dim(1) * weight).reshape([b, g, h, w]);
    let nats = nats.reshape([b, 1, 1, 1]);
    let skip = log_likelihood(window_sum(pixel.clone(), window), nats.clone(), lit.clone());
    (pooled_posterior(pixel, nats, lit, pool), skip)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evidence_tensors::testing::{assert_the_gradient_is_the_derivative, noisy_with_a_dark_pixel, prototype_flim_matrix};
    use crate::lifetime::{evidence_at, frame_templates, LifetimeInput, LifetimeNetConfig};
    use crate::sensor_tensors::SensorTensors;
    use tcsense_sensor::waveform::{decay_bin_averages, Cycle, IrfKernel};

    /// A noisy 8×8 frame of lifetimes 0.6–6 ns on a background, at an onset of its own, through
    /// the prototype codes (heterodyne 4, physical IRF), pixel 9 dark, and its sensor.
    fn frame(device: &Device) -> (MeasurementMatrix, Vec<f32>, (usize, usize)) {
        let a = prototype_flim_matrix();
        let (h, w, t) = (8, 8, a.bins());
        let c = Cycle::new(t, a.bin_width_s());
        let k = IrfKernel::gaussian(c, 0.5e-9);
        let mut x = vec![0f32; t * h * w];
        for p in 0..h * w {
            let tau = 0.6e-9 * 10f64.powf((p % w) as f64 / (w - 1) as f64);
            let amp = 200.0 + 150.0 * (p / w) as f64;
            let curve = k.apply(&decay_bin_averages(c, tau, 11e-9));
            for (j, v) in curve.iter().enumerate() {
                x[j * h * w + p] = (amp * v + 0.3) as f32;
            }
        }
        let st = SensorTensors::new(&a, h, w, device).unwrap();
        let y: Vec<f32> = st.forward(Tensor::<4>::from_data(TensorData::new(x, [1, t, h, w]), device)).into_data().try_into_vec().unwrap();
        (a, noisy_with_a_dark_pixel(y, h * w, 9), (h, w))
    }

    /// What the fit found on the frame that the copy takes as given: the decays at its instrument
    /// `[1, T, G]` and `ν` `[1]`.
    fn fit_of(a: &MeasurementMatrix, y: &[f32], (h, w): (usize, usize), opts: &TapFitOptions, device: &Device) -> (Tensor<3>, Tensor<1>) {
        let ya = ndarray::ArrayView3::from_shape((4, h, w), y).unwrap();
        let templates = frame_templates(&ya, a, opts);
        let (e, _) = evidence_at(&ya, &templates, 2, &[]);
        (
            decays_tensor(a, &[templates.instrument()], opts, device),
            Tensor::<1>::from_data(TensorData::new(vec![1.0 / (2.0 * e.noise)], [1]), device),
        )
    }

    /// The tensor copy gives the fit's evidence: the same log-likelihoods and pooled posteriors
    /// at every pixel, the dark one included.
    #[test]
    fn the_copy_equals_the_fit_in_value() {
        let device = Device::flex();
        let (a, y, (h, w)) = frame(&device);
        let t = a.bins();
        let cfg =
            LifetimeNetConfig::new(4, t).with_base_width(4).with_levels(2).with_input(LifetimeInput::Costs).with_points(24).with_pool(5);
        let net = cfg.init(&device);
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let yt = Tensor::<4>::from_data(TensorData::new(y.clone(), [1, 4, h, w]), &device);
        let (features, skip) = net.evidence(yt.clone(), &st);
        let opts = net.fit_options();
        let (decays, nats) = fit_of(&a, &y, (h, w), &opts, &device);
        let (post, copy) = lifetime_evidence(yt, st.a.clone(), st.block, decays, nats, opts.window, 5, opts.background);
        assert_eq!(post.dims(), [1, 5, h, w]);
        let v = |x: Tensor<4>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
        let (fit_skip, copy_skip) = (v(skip), v(copy));
        let scale = fit_skip.iter().fold(0f32, |m, x| m.max(x.abs()));
        assert!(scale > 10.0, "the frame discriminates lifetimes: {scale} nats");
        for (i, (f, c)) in fit_skip.iter().zip(&copy_skip).enumerate() {
            assert!((f - c).abs() <= 1e-3 * scale, "skip {i}: fit {f}, copy {c}");
        }
        let (fit_post, copy_post) = (v(features.narrow(1, 0, 5)), v(post));
        for (i, (f, c)) in fit_post.iter().zip(&copy_post).enumerate() {
            assert!((f - c).abs() <= 2e-3, "posterior {i}: fit {f}, copy {c}");
        }
        assert!(fit_post.iter().skip(9).step_by(h * w).all(|&v| v == 0.0), "the dark pixel has no posterior");
    }

    /// The gradient in `A` is the copy's derivative: autodiff's directional derivative of a
    /// weighted sum of the evidence equals central differences.
    #[test]
    fn the_gradient_in_a_is_the_derivative() {
        let device = Device::flex().autodiff();
        let (a, y, (h, w)) = frame(&device);
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let opts = LifetimeNetConfig::new(4, a.bins()).with_input(LifetimeInput::Costs).with_points(24).init(&device).fit_options();
        let (decays, nats) = fit_of(&a, &y, (h, w), &opts, &device);
        let g = 24;
        let wk: Vec<f32> = (0..g * h * w).map(|i| ((i * 40503) % 17) as f32 / 17.0).collect();
        assert_the_gradient_is_the_derivative(&st.a, 1e-3, |a_t| {
            let yt = Tensor::<4>::from_data(TensorData::new(y.clone(), [1, 4, h, w]), &device);
            let (post, skip) = lifetime_evidence(yt, a_t, st.block, decays.clone(), nats.clone(), 3, 2, true);
            let wt = Tensor::<4>::from_data(TensorData::new(wk.clone(), [1, g, h, w]), &device);
            (skip * wt.clone()).sum() + (post * wt.narrow(1, 0, g / 2)).sum().mul_scalar(10.0)
        });
    }

    /// Deep sensing's path: on a sensor whose `A` is learnable ([`SensorTensors::with_matrix`]),
    /// the network's training output on the fit's evidence has the fit's values and a gradient
    /// in `A` (before the copy, the evidence was a constant and the codes learned nothing from
    /// the lifetime loss).
    #[test]
    fn the_training_output_reaches_the_codes() {
        use crate::net::Network;
        let device = Device::flex().autodiff();
        let (a, y, (h, w)) = frame(&device);
        let t = a.bins();
        let net =
            LifetimeNetConfig::new(4, t).with_base_width(4).with_levels(2).with_input(LifetimeInput::Costs).with_points(24).init(&device);
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let a_t = st.a.clone().reshape([st.a.dims()[1], 4, t]).require_grad();
        let learnable = st.clone().with_matrix(a_t.clone());
        let yt = || Tensor::<4>::from_data(TensorData::new(y.clone(), [1, 4, h, w]), &device);
        let fixed = net.train_output(yt(), &st);
        let out = net.train_output(yt(), &learnable);
        let v = |x: Tensor<4>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
        assert_eq!(v(fixed.clone()), v(out.clone()), "the same values");
        let g: Vec<f32> = a_t.grad(&out.narrow(1, 0, 1).sum().backward()).expect("a gradient in A").into_data().try_into_vec().unwrap();
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| v.abs() > 0.0), "the mean lifetime moves with A");
        assert!(a_t.grad(&fixed.narrow(1, 0, 1).sum().backward()).is_none(), "a fixed sensor gives A no gradient");
    }
}
