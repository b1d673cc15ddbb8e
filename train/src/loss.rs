//! Training losses (paper Table 3): RMSE for FLIm cubes, RMSE + MAE for LiDAR cubes; for
//! depth networks a masked L1 on the depth (in units of the range) where the truth has a
//! return, plus the binary cross-entropy of the confidence against "has a return".

use burn::tensor::activation::relu;
use burn::tensor::Tensor;

use crate::config::{ConfidenceLoss, LifetimeError, Loss};

/// The loss of a batch.
///
/// # Shapes
/// - `pred`, `truth`: `[B, T, H, W]` → `[1]`
pub fn loss_fn(loss: Loss, pred: Tensor<4>, truth: Tensor<4>) -> Tensor<1> {
    let d = pred - truth.clone();
    let rmse = d.clone().powi_scalar(2).mean().sqrt();
    match loss {
        Loss::Rmse => rmse,
        Loss::RmseMae => rmse + d.abs().mean(),
        Loss::RmseMaePixel => {
            let dw = d.clone() * pixel_weights(truth);
            rmse + d.abs().mean() + dw.clone().powi_scalar(2).mean().sqrt() + dw.abs().mean()
        }
    }
}

/// Floor of a pixel's peak in [`pixel_weights`], as a fraction of its item's brightest bin: a
/// pixel at a twentieth of the brightest counts as much as the brightest, a darker one less.
pub const PIXEL_FLOOR: f64 = 0.05;

/// `1 / (max_t x + PIXEL_FLOOR · max_{t,h,w} x)` per pixel: divides a waveform by its peak.
///
/// # Shapes
/// - `truth`: `[B, T, H, W]` → `[B, 1, H, W]`
pub fn pixel_weights(truth: Tensor<4>) -> Tensor<4> {
    let peak = truth.max_dim(1); // [B, 1, H, W]
    let item = peak.clone().max_dim(2).max_dim(3); // [B, 1, 1, 1]
    (peak + item.mul_scalar(PIXEL_FLOOR).add_scalar(1e-12)).recip()
}

/// The earth mover's distance, in bins, between every pixel's predicted and true waveform, each
/// normalised to unit sum (the prediction's negative part dropped), averaged over the pixels
/// whose truth carries at least [`EMD_FLOOR`] of its item's brightest pixel's signal: every
/// such pixel counts the same, however dim. On the time axis the distance is
/// `Σ_t |P_t − Q_t|` of the two cumulative sums: a return moved by `d` bins costs `d`, two
/// exponential decays of one onset cost the difference of their lifetimes in bins, and mass
/// the prediction puts far from the truth (a false return, noise) costs its share times its
/// distance.
///
/// # Shapes
/// - `pred`, `truth`: `[B, T, H, W]` → `[1]`
pub fn waveform_emd(pred: Tensor<4>, truth: Tensor<4>) -> Tensor<1> {
    let p = relu(pred);
    let p = p.clone() / p.sum_dim(1).add_scalar(1e-12); // [B, T, H, W]
    let q = truth.clamp_min(0.0);
    let energy = q.clone().sum_dim(1); // [B, 1, H, W]
    let q = q / energy.clone().clamp_min(1e-12);
    let brightest = energy.clone().max_dim(2).max_dim(3); // [B, 1, 1, 1]
    let mask = energy.greater_equal(brightest.mul_scalar(EMD_FLOOR).clamp_min(1e-12)).float(); // [B, 1, H, W]
    let emd = (p - q).cumsum(1).abs().sum_dim(1); // [B, 1, H, W]
    (emd * mask.clone()).sum() / mask.sum().add_scalar(1e-12)
}

/// A pixel counts in [`waveform_emd`] where its true signal is at least this fraction of its
/// item's brightest pixel's (a dark surface at a hundredth of the albedo still counts; a pixel
/// without a return does not).
pub const EMD_FLOOR: f64 = 1e-3;

/// Weight of [`waveform_emd`] (in bins) beside the cube's loss under `--objective range` or
/// `lifetime`: a return a bin away costs about what the cube's loss is at the end of a
/// training.
pub const EMD_WEIGHT: f64 = 0.05;

/// The depth loss of a batch.
///
/// # Shapes
/// - `pred`: `[B, 2K, H, W]` (depth in metres, confidence logits), `depth`: `[B, K, H, W]` (m,
///   0 where none), `mask`: `[B, K, H, W]` (1 where the truth has a return) → `[1]`
pub fn depth_loss(pred: Tensor<4>, depth: Tensor<4>, mask: Tensor<4>, range_m: f64) -> Tensor<1> {
    let k = depth.dims()[1];
    let d = pred.clone().narrow(1, 0, k);
    let logits = pred.clone().narrow(1, k, k);
    let count = mask.clone().sum().add_scalar(1.0);
    let l1 = ((d - depth.clone()).abs() * mask.clone()).sum() / count.clone() / range_m;
    // BCE with logits, stable: max(l, 0) − l·t + log(1 + e^{−|l|})
    let bce = relu(logits.clone()) - logits.clone() * mask.clone() + logits.abs().neg().exp().add_scalar(1.0).log();
    let c = pred.dims()[1];
    if c == 2 * k {
        return l1 + bce.mean();
    }
    // the score volume's log-probabilities [B, K·T, H, W] against the true range split between
    // the two nearest bin centres (their expectation is the true range)
    let t = (c - 2 * k) / k;
    let logp = pred.narrow(1, 2 * k, k * t);
    let [b, _, h, w] = depth.dims();
    let u = depth.clone().mul_scalar(t as f64 / range_m).sub_scalar(0.5).clamp(0.0, (t - 1) as f64); // [B, K, H, W] in bins
    let centres: Vec<f32> = (0..t).map(|j| j as f32).collect();
    let bins = Tensor::<1>::from_floats(centres.as_slice(), &u.device()).reshape([1, 1, t, 1, 1]);
    // hat function max(0, 1 − |t − u|): weight 1 − frac at ⌊u⌋, frac at ⌊u⌋ + 1
    let label = (bins - u.reshape([b, k, 1, h, w])).abs().neg().add_scalar(1.0).clamp_min(0.0); // [B, K, T, H, W]
    let ce = (label * logp.reshape([b, k, t, h, w])).sum_dim(2).reshape([b, k, h, w]).neg() * mask;
    l1 + bce.mean() + ce.sum() / count * CE_WEIGHT
}

/// The loss of a depth network on a grid of candidate ranges (the U-Net on the range fit's
/// evidence): `−ln P(|r − r_true| ≤ tolerance)` under its posterior over the `C` candidates —
/// the posterior's mass within `tolerance` candidates of a true return (the grid is cyclic: the
/// candidates go round the code cycle), where the pixel has a return; of two returns, the more
/// probable one (the posterior is of one return: the first is either, and the fit's second
/// finds the other). With `tolerance` half a bin it is what the share of returns within half a
/// bin counts, and a sharp posterior whose mode is right costs nothing, however sharp (a
/// cross-entropy against the exact range made bright pixels, whose likelihood is sharper than
/// the candidates, dominate the loss with their calibration). Plus the binary cross-entropy of
/// the first return's confidence against "has a return". The network's second return is the
/// fit's, so nothing else is learned. With `cap`, a pixel's cross-entropy is held at `cap`
/// nats (no gradient beyond it): a pixel whose likelihood is sharp and wrong costs the cap and
/// does not bend the learned prior of every other pixel to it.
///
/// # Shapes
/// - `pred`: `[B, 2K + C, H, W]` (depth in metres, confidence logits, log-posterior over the
///   candidates), `depth`: `[B, K, H, W]` (m, 0 where none), `mask`: `[B, K, H, W]` (1 where
///   the truth has a return), `grid`: `(scale, offset)`, a range `r` sits at candidate
///   `r·scale − offset`; `tolerance` in candidates → `[1]`
pub fn depth_grid_loss(
    pred: Tensor<4>,
    depth: Tensor<4>,
    mask: Tensor<4>,
    (scale, offset): (f64, f64),
    tolerance: f64,
    cap: Option<f64>,
) -> Tensor<1> {
    const MISSING: f64 = 1e9; // (a return that is not there is never the most probable)
    let [b, k, h, w] = depth.dims();
    let c = pred.dims()[1] - 2 * k;
    let logp = pred.clone().narrow(1, 2 * k, c); // [B, C, H, W]
    let logit = pred.narrow(1, k, 1); // [B, 1, H, W]
    let any = mask.clone().narrow(1, 0, 1); // [B, 1, H, W]
    let u = depth.mul_scalar(scale).sub_scalar(offset).reshape([b, k, 1, h, w]);
    let index: Vec<f32> = (0..c).map(|j| j as f32).collect();
    let index = Tensor::<1>::from_floats(index.as_slice(), &logp.device()).reshape([1, 1, c, 1, 1]);
    let d = (index - u).abs(); // [B, K, C, H, W], within C
    let d = d.clone().min_pair(d.neg().add_scalar(c as f64)); // cyclic distance
    let near = d.lower_equal_elem(tolerance);
    // ln of the mass near each return: a log-sum-exp over the candidates near it
    let x = logp.reshape([b, 1, c, h, w]).expand([b, k, c, h, w]).mask_fill(near.bool_not(), -1e4);
    let top = x.clone().max_dim(2); // [B, K, 1, H, W]
    let lse = (x - top.clone()).exp().sum_dim(2).log() + top;
    let nll = lse.reshape([b, k, h, w]).neg();
    let nll = (nll * mask.clone() + mask.neg().add_scalar(1.0).mul_scalar(MISSING)).min_dim(1); // [B, 1, H, W]
                                                                                                // (held at the cap: no gradient from a pixel beyond it)
    let nll = match cap {
        Some(c) => nll.clamp_max(c),
        None => nll,
    } * any.clone();
    let count = any.clone().sum().add_scalar(1.0);
    let bce = relu(logit.clone()) - logit.clone() * any + logit.abs().neg().exp().add_scalar(1.0).log();
    nll.sum() / count + bce.mean()
}

/// Weight of the score volume's cross-entropy in [`depth_loss`] (an error of one bin costs
/// the L1 term `1/T`; the cross-entropy of a two-bin split is at least ln 2).
pub const CE_WEIGHT: f64 = 0.1;

/// How a lifetime network's loss is taken: the terms its run's config sets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LifetimeTerms {
    /// The weight of the grid's cross-entropy ([`GRID_CE_WEIGHT`] by default).
    pub ce_weight: f64,
    /// How the lifetimes' error is measured.
    pub error: LifetimeError,
    /// How a grid network's confidence is trained.
    pub confidence: ConfidenceLoss,
}

impl Default for LifetimeTerms {
    /// The terms of configs written before the choices.
    fn default() -> Self {
        LifetimeTerms { ce_weight: GRID_CE_WEIGHT, error: LifetimeError::Ns, confidence: ConfidenceLoss::Stalled }
    }
}

/// The lifetime loss of a batch: mean absolute error of `τ_m` where the pixel holds a
/// fluorophore (in ns, or of `ln τ` times [`LOG_ERROR_NS`]: `terms.error`), half that of `τ₁`
/// and `τ₂`, the error of `α₁` where the two components differ, and the binary cross-entropy
/// of the confidence against "holds a fluorophore". A network on a lifetime grid (`grid`:
/// `ln τ₀` in ns and the step) appends its log-posterior over the grid, whose cross-entropy
/// against the true `τ_m` split between its two neighbouring points adds `terms.ce_weight`
/// times its mean over the fluorophore, and whose confidence weighs a missed fluorophore
/// [`COVERAGE_WEIGHT`] times (written as `terms.confidence` says).
///
/// # Shapes
/// - `pred`: `[B, 5, H, W]` (`τ_m`, `τ₁`, `τ₂` in ns, `α₁`, confidence logit) or
///   `[B, 5 + G, H, W]` (then the log-posterior), `labels`: `[B, 5, H, W]` (the same, 0 where
///   unknown, then the signal mask), `distinct`: `[B, 1, H, W]` (1 where `τ₁ ≠ τ₂`) → `[1]`
pub fn lifetime_loss(pred: Tensor<4>, labels: Tensor<4>, distinct: Tensor<4>, grid: Option<(f64, f64)>, terms: LifetimeTerms) -> Tensor<1> {
    let mask = labels.clone().narrow(1, 4, 1); // [B, 1, H, W]
    let count = mask.clone().sum().add_scalar(1.0);
    let err = |c: usize| (pred.clone().narrow(1, c, 1) - labels.clone().narrow(1, c, 1)).abs() * mask.clone();
    // (the labels are 0 where unknown: clamped before the logarithm, and masked)
    let log_err = |c: usize| {
        let ln = |x: Tensor<4>| x.clamp_min(LOG_FLOOR_NS).log();
        (ln(pred.clone().narrow(1, c, 1)) - ln(labels.clone().narrow(1, c, 1))).abs().mul_scalar(LOG_ERROR_NS) * mask.clone()
    };
    let tau_err = |c: usize| match terms.error {
        LifetimeError::Ns => err(c),
        LifetimeError::Log => log_err(c),
    };
    let l1 = (tau_err(0) + (tau_err(1) + tau_err(2)) * 0.5 + err(3) * distinct).sum() / count.clone();
    let logits = pred.clone().narrow(1, 4, 1);
    let c = pred.dims()[1];
    match grid {
        Some((l0, step)) if c > OUTPUTS => {
            let g = c - OUTPUTS;
            let logp = pred.narrow(1, OUTPUTS, g); // [B, G, H, W]
                                                   // the true τ_m on the grid (0 where there is none; masked out)
            let tau = labels.narrow(1, 0, 1).clamp_min(1e-6);
            let u = tau.log().sub_scalar(l0).div_scalar(step).clamp(0.0, (g - 1) as f64); // [B, 1, H, W]
            let index: Vec<f32> = (0..g).map(|j| j as f32).collect();
            let index = Tensor::<1>::from_floats(index.as_slice(), &u.device()).reshape([1, g, 1, 1]);
            let label = (index - u).abs().neg().add_scalar(1.0).clamp_min(0.0); // hat weights [B, G, H, W]
            let ce = (label * logp).sum_dim(1).neg() * mask.clone();
            // the confidence weighs a missed fluorophore COVERAGE_WEIGHT times a false one: a
            // pixel gets a lifetime where the posterior of a fluorophore is above 1/(1 + w)
            let softplus = |x: Tensor<4>| relu(x.clone()) + x.abs().neg().exp().add_scalar(1.0).log();
            let weighted = match terms.confidence {
                ConfidenceLoss::Stalled => {
                    softplus(logits.clone().neg()) * mask.clone() * COVERAGE_WEIGHT + softplus(logits) * mask.neg().add_scalar(1.0)
                }
                // softplus(−l) = softplus(l) − l
                ConfidenceLoss::Weighted => {
                    // (burn's softplus, ln(1 + eˡ): its gradient at 0 is ½, where the form above
                    // has relu's and |l|'s, 0)
                    let factor = mask.clone().mul_scalar(COVERAGE_WEIGHT - 1.0).add_scalar(1.0); // w·m + 1 − m
                    burn::tensor::activation::softplus(logits.clone(), 1.0) * factor - logits * mask.mul_scalar(COVERAGE_WEIGHT)
                }
            };
            l1 + weighted.mean() + ce.sum() / count * terms.ce_weight
        }
        _ => {
            let bce = relu(logits.clone()) - logits.clone() * mask + logits.abs().neg().exp().add_scalar(1.0).log();
            l1 + bce.mean()
        }
    }
}

/// Channels of a lifetime prediction before any log-posterior.
const OUTPUTS: usize = 5;

/// [`LifetimeError::Log`]: the error of `ln τ` is counted as this many ns (an error of 1 %
/// as 0.02 ns: about what the ns error gives it at the training data's typical 2 ns).
pub const LOG_ERROR_NS: f64 = 2.0;

/// [`LifetimeError::Log`]: lifetimes (predicted or true) are taken as at least this many ns
/// before their logarithm.
const LOG_FLOOR_NS: f64 = 1e-3;

/// Weight of the lifetime grid's cross-entropy in [`lifetime_loss`].
pub const GRID_CE_WEIGHT: f64 = 0.2;

/// A lifetime network on a grid: weight of a missed fluorophore pixel in the confidence's
/// cross-entropy against a false one (coverage matters more to a lifetime map than a few
/// background pixels with a lifetime, which the intensity shows as dark anyway).
pub const COVERAGE_WEIGHT: f64 = 8.0;

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    /// The grid loss is the posterior's mass within the tolerance of the truth (across the
    /// cycle's wrap too), whatever its shape there, and its confidence term is the BCE.
    #[test]
    fn the_depth_grid_loss_counts_the_mass_near_the_truth_on_the_cyclic_grid() {
        let device = Device::flex();
        // C = 4 candidates, K = 1, two pixels: one return at candidate 3.5 (candidates 3 and 0
        // within 0.5 across the wrap), and none
        let loss = |first: [f32; 4], logit: f32| -> f32 {
            let mut v = vec![0.0f32, 0.0, logit, -2.0];
            for &p in first.iter() {
                v.push(p.ln());
                v.push(-(4f32).ln());
            }
            let pred = Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 6, 1, 2]), &device);
            let depth = Tensor::<4>::from_floats([[[[3.5, 0.0]]]], &device);
            let mask = Tensor::<4>::from_floats([[[[1.0, 0.0]]]], &device);
            depth_grid_loss(pred, depth, mask, (1.0, 0.0), 0.5, None).into_scalar()
        };
        let bce = (2f32).ln() + (1.0 + (-2f32).exp()).ln();
        // all the mass near the truth, split or on one side: no cost but the confidence's
        for p in [[0.5, 1e-6, 1e-6, 0.5], [1.0 - 2e-6, 1e-6, 1e-6, 1e-6]] {
            assert!((loss(p, 0.0) - bce / 2.0).abs() < 1e-4, "{p:?}: {}", loss(p, 0.0));
        }
        // a quarter of it: ln 4 over the one pixel with a return (count 2)
        let quarter = loss([0.125, 0.375, 0.375, 0.125], 0.0);
        assert!((quarter - ((4f32).ln() / 2.0 + bce / 2.0)).abs() < 1e-4, "{quarter}");
    }

    /// Held at a cap, a pixel's cross-entropy costs at most the cap and, beyond it, gives no
    /// gradient to its log-posterior; below the cap the loss and its gradient are unchanged.
    #[test]
    fn a_capped_grid_loss_holds_a_hopeless_pixel_at_the_cap_without_gradient() {
        let device = Device::flex().autodiff();
        // one pixel, K = 1, C = 4, the return at candidate 1.0 (only candidate 1 within 0.5)
        let run = |mass_at_truth: f32, cap: Option<f64>| -> (f32, Vec<f32>) {
            let rest = (1.0 - mass_at_truth) / 3.0;
            let mut v = vec![1.0f32, 0.0];
            v.extend([rest, mass_at_truth, rest, rest].map(f32::ln));
            let pred = Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 6, 1, 1]), &device).require_grad();
            let depth = Tensor::<4>::from_floats([[[[1.0]]]], &device);
            let mask = Tensor::<4>::from_floats([[[[1.0]]]], &device);
            let l = depth_grid_loss(pred.clone(), depth, mask, (1.0, 0.0), 0.5, cap);
            let grads = l.backward();
            let g: Vec<f32> = pred.grad(&grads).expect("a gradient").to_data().try_to_vec::<f32>().unwrap();
            (l.into_scalar(), g[2..].to_vec())
        };
        // the confidence's term at logit 0, over the one pixel
        let bce = (2f32).ln();
        // hopeless: e^-10 of the mass at the truth costs 10 nats (over a count of 2), held at 3
        let (free, free_grad) = run((-10f32).exp(), None);
        let (held, held_grad) = run((-10f32).exp(), Some(3.0));
        assert!((free - (10.0 / 2.0 + bce)).abs() < 1e-3, "{free}");
        assert!((held - (3.0 / 2.0 + bce)).abs() < 1e-3, "{held}");
        assert!(free_grad.iter().any(|g| g.abs() > 0.1), "{free_grad:?}");
        assert!(held_grad.iter().all(|g| *g == 0.0), "{held_grad:?}");
        // within the cap nothing changes
        let (a, ga) = run(0.5, None);
        let (b, gb) = run(0.5, Some(3.0));
        assert!((a - b).abs() < 1e-6 && ga == gb, "{a} {b} {ga:?} {gb:?}");
    }

    /// A return moved by two bins costs two; a prediction with a fifth of its mass three bins
    /// off costs 0.6; an all-dark pixel does not count; scale does not matter.
    #[test]
    fn the_waveform_distance_is_the_shift_in_bins() {
        let device = Device::flex();
        let cube = |pixels: [[f32; 6]; 3]| {
            let v: Vec<f32> = (0..6).flat_map(|t| pixels.iter().map(move |p| p[t])).collect();
            Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 6, 1, 3]), &device)
        };
        let truth = cube([[0.0, 1.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0], [0.0; 6]]);
        let pred = cube([[0.0, 0.0, 0.0, 7.0, 0.0, 0.0], [0.0, 0.0, 0.8, 0.0, 0.0, 0.2], [0.0, 3.0, 0.0, 0.0, 0.0, 0.0]]);
        let l: f32 = waveform_emd(pred, truth.clone()).into_scalar();
        assert!((l - (2.0 + 0.6) / 2.0).abs() < 1e-5, "{l}");
        // negative values are dropped, not counted as mass
        let pred = cube([[0.0, 2.0, -5.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0], [0.0; 6]]);
        let l: f32 = waveform_emd(pred, truth).into_scalar();
        assert!(l.abs() < 1e-5, "{l}");
        // two decays of one onset: the difference of their means
        let decay = |tau: f32| -> Vec<f32> { (0..64).map(|t| (-(t as f32) / tau).exp()).collect() };
        let (a, b) = (decay(3.0), decay(5.0));
        let mean = |d: &[f32]| d.iter().enumerate().map(|(t, v)| t as f32 * v).sum::<f32>() / d.iter().sum::<f32>();
        let t = |d: Vec<f32>| Tensor::<4>::from_data(burn::tensor::TensorData::new(d, [1, 64, 1, 1]), &device);
        let l: f32 = waveform_emd(t(b.clone()), t(a.clone())).into_scalar();
        assert!((l - (mean(&b) - mean(&a))).abs() < 1e-3, "{l} vs {}", mean(&b) - mean(&a));
    }

    #[test]
    fn rmse_and_mae_values() {
        let device = Device::flex();
        let pred = Tensor::<4>::from_floats([[[[1.0, 2.0], [3.0, 4.0]]]], &device);
        let truth = Tensor::<4>::from_floats([[[[1.0, 0.0], [3.0, 0.0]]]], &device);
        // differences 0, 2, 0, 4: RMSE = sqrt(20/4), MAE = 6/4
        let rmse: f32 = loss_fn(Loss::Rmse, pred.clone(), truth.clone()).into_scalar();
        let both: f32 = loss_fn(Loss::RmseMae, pred, truth).into_scalar();
        assert!((rmse - 5f32.sqrt()).abs() < 1e-6, "{rmse}");
        assert!((both - (5f32.sqrt() + 1.5)).abs() < 1e-6, "{both}");
    }

    #[test]
    fn the_pixel_loss_weighs_every_waveform_by_its_peak() {
        let device = Device::flex();
        // T = 2, two pixels: a bright one (peak 1) off by 0.1 in one bin and a dim one (peak
        // 0.1) off by 0.01: the same shape error, ten times smaller in absolute terms
        let truth = Tensor::<4>::from_floats([[[[1.0, 0.1]], [[0.0, 0.0]]]], &device); // [1, 2, 1, 2]
        let pred = Tensor::<4>::from_floats([[[[1.1, 0.11]], [[0.0, 0.0]]]], &device);
        let w: Vec<f32> = pixel_weights(truth.clone()).into_data().try_into_vec::<f32>().unwrap();
        assert!((w[0] - 1.0 / 1.05).abs() < 1e-6 && (w[1] - 1.0 / 0.15).abs() < 1e-5, "{w:?}");
        let l: f32 = loss_fn(Loss::RmseMaePixel, pred.clone(), truth.clone()).into_scalar();
        let plain: f32 = loss_fn(Loss::RmseMae, pred, truth).into_scalar();
        // weighted differences 0.1/1.05 and 0.01/0.15 in 2 of 4 entries
        let (a, b) = (0.1f32 / 1.05, 0.01f32 / 0.15);
        let want = plain + ((a * a + b * b) / 4.0).sqrt() + (a + b) / 4.0;
        assert!((l - want).abs() < 1e-6, "{l} vs {want}");
    }

    #[test]
    fn depth_loss_masks_and_scores_confidence() {
        let device = Device::flex();
        // K = 1, two pixels: one return at 3 m (predicted 4 m, logit 0), one without (logit 0)
        let pred = Tensor::<4>::from_floats([[[[4.0, 9.0]], [[0.0, 0.0]]]], &device); // [1, 2, 1, 2]
        let depth = Tensor::<4>::from_floats([[[[3.0, 0.0]]]], &device);
        let mask = Tensor::<4>::from_floats([[[[1.0, 0.0]]]], &device);
        let l: f32 = depth_loss(pred, depth, mask, 10.0).into_scalar();
        // L1 = |4 − 3| / (1 + 1) / 10 = 0.05 (the pixel without a return does not count); BCE = ln 2
        assert!((l - (0.05 + 2f32.ln())).abs() < 1e-6, "{l}");
    }

    #[test]
    fn the_score_volume_loss_adds_the_cross_entropy_of_the_split_bins() {
        let device = Device::flex();
        // K = 1, T = 4 bins over 8 m (centres 1, 3, 5, 7 m); one pixel with a return at 4 m
        // (half way between bins 1 and 2), predicted 4 m, logit 0, log-probabilities ln ¼
        let mut v = vec![4.0f32, 0.0];
        v.extend([0.25f32.ln(); 4]);
        let pred = Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 6, 1, 1]), &device);
        let depth = Tensor::<4>::from_floats([[[[4.0]]]], &device);
        let mask = Tensor::<4>::from_floats([[[[1.0]]]], &device);
        let l: f32 = depth_loss(pred, depth, mask, 8.0).into_scalar();
        // L1 0, BCE ln 2, CE −(½ ln ¼ + ½ ln ¼) = ln 4, over 1 + 1
        let want = 2f64.ln() + 4f64.ln() / 2.0 * CE_WEIGHT;
        assert!((l as f64 - want).abs() < 1e-5, "{l} vs {want}");
    }

    #[test]
    fn lifetime_loss_masks_and_weighs_the_components() {
        let device = Device::flex();
        // two pixels: a fluorophore (τ_m 2 ns predicted 2.5; τ₁ 1 vs 1.5, τ₂ 3 vs 3, α 0.4 vs
        // 0.5, distinct) and background (every lifetime wrong, does not count); logits 0
        let pred = Tensor::<4>::from_floats([[[[2.5, 9.0]], [[1.5, 9.0]], [[3.0, 9.0]], [[0.4, 0.9]], [[0.0, 0.0]]]], &device);
        let labels = Tensor::<4>::from_floats([[[[2.0, 0.0]], [[1.0, 0.0]], [[3.0, 0.0]], [[0.5, 0.0]], [[1.0, 0.0]]]], &device);
        let distinct = Tensor::<4>::from_floats([[[[1.0, 0.0]]]], &device);
        let l: f32 = lifetime_loss(pred, labels, distinct, None, LifetimeTerms::default()).into_scalar();
        // (0.5 + 0.5·(0.5 + 0) + 0.1) / (1 + 1) + ln 2
        assert!((l - (0.85 / 2.0 + 2f32.ln())).abs() < 1e-6, "{l}");
    }

    /// On a grid, the log-posterior's cross-entropy adds `ce_weight` times its mean over the
    /// fluorophore pixels: none at weight 0.
    #[test]
    fn the_grid_cross_entropy_is_weighed_as_asked() {
        let device = Device::flex();
        // one fluorophore pixel, τ_m = 2 ns predicted exactly, logit 0; a grid of 4 points at
        // ln τ = 0, 1, 2, 3 ns (ln τ₀ = 0, step 1): the truth at u = ln 2, split between points
        // 0 and 1; log-posterior ln ¼ at every point
        let mut v = vec![2.0f32, 2.0, 2.0, 1.0, 0.0];
        v.extend([0.25f32.ln(); 4]);
        let pred = || Tensor::<4>::from_data(burn::tensor::TensorData::new(v.clone(), [1, 9, 1, 1]), &device);
        let labels = || Tensor::<4>::from_floats([[[[2.0]], [[2.0]], [[2.0]], [[1.0]], [[1.0]]]], &device);
        let distinct = || Tensor::<4>::from_floats([[[[0.0]]]], &device);
        let at = |w: f64| -> f64 {
            lifetime_loss(pred(), labels(), distinct(), Some((0.0, 1.0)), LifetimeTerms { ce_weight: w, ..LifetimeTerms::default() })
                .into_scalar::<f32>() as f64
        };
        // the confidence: softplus(0)·COVERAGE_WEIGHT = 8 ln 2; the cross-entropy ln 4 over 1 + 1
        let base = COVERAGE_WEIGHT * 2f64.ln();
        assert!((at(0.0) - base).abs() < 1e-5, "{}", at(0.0));
        assert!((at(0.2) - (base + 0.2 * 4f64.ln() / 2.0)).abs() < 1e-5, "{}", at(0.2));
        assert!((at(1.0) - (base + 4f64.ln() / 2.0)).abs() < 1e-5, "{}", at(1.0));
    }

    /// The two ways of writing the confidence's cross-entropy have the same value at every
    /// logit; at the untrained head (logit 0) the first's gradient vanishes (why the networks
    /// trained with it never learned a confidence) and the weighted one's is
    /// `((1 − m) − w·m) / 2` per pixel over the pixels.
    #[test]
    fn the_weighted_confidence_loss_is_the_stalled_one_with_a_gradient_at_zero() {
        let device = Device::flex();
        // three pixels on a grid of 2 points (the log-posterior ln ½ each): two fluorophores of
        // 2 ns predicted exactly, one background; the logits as given
        let pred = |logits: [f32; 3]| {
            let mut v = vec![2.0f32, 2.0, 0.0, 2.0, 2.0, 0.0, 2.0, 2.0, 0.0, 1.0, 1.0, 0.0];
            v.extend(logits);
            v.extend([0.5f32.ln(); 6]);
            Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 7, 1, 3]), &device)
        };
        let labels = || {
            let v = vec![2.0f32, 2.0, 0.0, 2.0, 2.0, 0.0, 2.0, 2.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0];
            Tensor::<4>::from_data(burn::tensor::TensorData::new(v, [1, 5, 1, 3]), &device)
        };
        let distinct = || Tensor::<4>::zeros([1, 1, 1, 3], &device);
        let terms = |confidence| LifetimeTerms { ce_weight: 0.0, error: LifetimeError::Ns, confidence };
        for logits in [[0.0f32, 0.0, 0.0], [-3.0, 1.5, 2.0], [20.0, -20.0, 0.5]] {
            let at = |c| lifetime_loss(pred(logits), labels(), distinct(), Some((0.0, 1.0)), terms(c)).into_scalar::<f32>();
            let (stalled, weighted) = (at(ConfidenceLoss::Stalled), at(ConfidenceLoss::Weighted));
            assert!((stalled - weighted).abs() <= 1e-5 * stalled.abs().max(1.0), "{logits:?}: {stalled} against {weighted}");
        }
        let ad = device.clone().autodiff();
        let gradient = |c| -> Vec<f32> {
            let p = Tensor::<4>::from_data(pred([0.0; 3]).into_data(), &ad).require_grad();
            let l = Tensor::<4>::from_data(labels().into_data(), &ad);
            let loss = lifetime_loss(p.clone(), l, Tensor::<4>::zeros([1, 1, 1, 3], &ad), Some((0.0, 1.0)), terms(c));
            let g = p.grad(&loss.backward()).expect("a gradient");
            g.narrow(1, 4, 1).into_data().try_into_vec().expect("f32")
        };
        assert!(gradient(ConfidenceLoss::Stalled).iter().all(|g| *g == 0.0), "{:?}", gradient(ConfidenceLoss::Stalled));
        let w = COVERAGE_WEIGHT as f32;
        let want = [-w / 2.0 / 3.0, -w / 2.0 / 3.0, 0.5 / 3.0];
        for (g, want) in gradient(ConfidenceLoss::Weighted).iter().zip(want) {
            assert!((g - want).abs() < 1e-5, "{g} against {want}");
        }
    }

    /// On `ln τ`, the error is relative: 2.5 for 2 ns and 5 for 4 ns cost the same,
    /// `LOG_ERROR_NS · ln 1.25` (half that of `τ₁`, `τ₂`), where in ns the second costs twice.
    #[test]
    fn the_log_lifetime_error_is_relative() {
        let device = Device::flex();
        let loss = |t: f32, error| {
            let pred = Tensor::<4>::from_floats([[[[t * 1.25]], [[t * 1.25]], [[t]], [[0.5]], [[0.0]]]], &device);
            let labels = Tensor::<4>::from_floats([[[[t]], [[t]], [[t]], [[0.5]], [[1.0]]]], &device);
            let distinct = Tensor::<4>::zeros([1, 1, 1, 1], &device);
            let terms = LifetimeTerms { error, ..LifetimeTerms::default() };
            lifetime_loss(pred, labels, distinct, None, terms).into_scalar::<f32>() as f64
        };
        let bce = 2f64.ln(); // logit 0, a fluorophore
        let want = LOG_ERROR_NS * 1.25f64.ln() * 1.5 / 2.0 + bce;
        for t in [2.0, 4.0] {
            assert!((loss(t, LifetimeError::Log) - want).abs() < 1e-5, "{t}: {}", loss(t, LifetimeError::Log));
        }
        let ns = |t: f64| 0.25 * t * 1.5 / 2.0 + bce;
        assert!((loss(4.0, LifetimeError::Ns) - ns(4.0)).abs() < 1e-5 && (loss(2.0, LifetimeError::Ns) - ns(2.0)).abs() < 1e-5);
    }
}
