//! The U-Net on the range fit's evidence ([`UnetInput::Costs`](crate::UnetInput::Costs)): a
//! photon-efficient depth decoder that is the fit where the fit is right and adds a spatial
//! prior where it is not (in the manner of the learned single-photon LiDAR decoders, Lindell
//! et al. 2018 and Peng et al. 2020, which decode a per-pixel evidence volume over the ranges
//! with a learned non-local prior, here on the compressive taps through the fit's templates).
//!
//! ```text
//! y [M, H, W] ──range fit, step 1 (tcsense_fits::depth)──▶ costs of every candidate range
//!     ──evidence (tcsense_fits::evidence)──▶ L_s [C, H, W]: the log-likelihood (nats) of the
//!                                            fit's 3×3 window (s = 0) and of 5×5, 9×9, 15×15
//!                                          features [4·C/pool + 2, H, W]: the posteriors of the
//!                                            pixel and of those windows, ln intensity, lit
//! features ──U-Net──1×1──▶ o [C, H, W] (zero at initialisation), confidence logit,
//!                           a log-weight o_s per wider window
//! w_s = e^{6·o_s − 6} (~0 at initialisation),  log-prior = 20·tanh(o/20)
//! logits = L_0 + Σ_{s≥1} w_s·L_s + log-prior;  u = the cyclic argmax, refined by a parabola
//! first return: the mode refined in the tap domain where the window's best candidate near it
//!               is its own (the fit's steps 3 and 4 seeded by the mode); else the mode
//! second return: the fit's, beside that first one
//! ```
//!
//! With `pool_like` N (`train unet --pool-like N`), `L_0` is the fit's 3×3 window's cost pooled
//! by likeness with the neighbouring 3×3 windows that tile N×N pixels, in the window's nats (the
//! cost `depth-fit-pooled` seeds from; [`tcsense_fits::depth::RangeTemplates::evidence`]): the
//! untrained network is that fit, and in dim light the prior adds to a surface's pooled evidence.
//!
//! The weights are a window learned pixel by pixel: the fit's 3×3 window is right in bright
//! light, a wider one in dim light (the fit itself with a 9×9 window takes the motorcycle's
//! median error at 0.005 of the full well from 4.4 to 0.9 bins, and loses precision at 0.1),
//! and none across a depth edge, which the network sees in the posteriors.
//!
//! The candidates go round the code cycle (`C = T·oversample`; the ranges wrap at the cycle's
//! unambiguous range), so the mode and its parabola are cyclic. Training takes the posterior's
//! cross-entropy against the true returns (each present return an equal share, split between
//! its two neighbouring candidates) and the confidence's against "has a return"
//! (`tcsense_train::loss::depth_loss`). The untrained network (a zero log-prior) is the fit
//! with its window's argmin as the seed: tested.

use burn::tensor::activation::log_softmax;
use burn::tensor::{Tensor, TensorData};
use ndarray::{Array4, ArrayView3, ArrayView4, Axis};
use tcsense_fits::depth::{CandidateGrid, DepthFitOptions, RangeTemplates, Seeds, SCALES};

use crate::evidence_tensors::{windowed_likelihood, with_gradient_of};
use crate::range_evidence::range_evidence;
use crate::sensor_tensors::SensorTensors;
use crate::unet::{conv1x1, trunk, Unet};

/// Bounds of the log of the learned weights of the wider windows' log-likelihoods.
pub const TEMPERATURE_RANGE: [f64; 2] = [-12.0, 3.0];

/// The offset of the wider windows' log-weights: `e^{−6}` of their log-likelihood at
/// initialisation, beside the fit's own window's at weight 1 (fixed: in bright light the fit's
/// window is the fit, sharper than any prior).
pub const WIDER_OFFSET: f64 = -6.0;

/// The gain of the wider windows' log-weights, `w_s = e^{G·o_s − 6}`: a head output of 1
/// gives weight 1 (with a gain of 1 the optimiser's steps of ~10⁻³ took longer than a training
/// to open a window).
pub const WIDER_GAIN: f64 = 6.0;

/// The bound of the learned log-prior (nats), `B·tanh(o/B)`: in dim light a few nats decide,
/// in bright light the likelihood is hundreds of nats sharp and no prior overrules it.
pub const PRIOR_BOUND: f64 = 20.0;

/// The confidence logit of a return that is not there (the second where the fit finds none).
const ABSENT: f32 = -30.0;

impl Unet {
    /// The settings of the range fit whose evidence the network reads: every lit pixel (no
    /// intensity floor: the network's confidence decides), the network's returns.
    pub fn fit_options(&self) -> DepthFitOptions {
        DepthFitOptions { pool_like: self.pool_like, ..DepthFitOptions::for_evidence(self.oversample, self.returns()) }
    }

    /// The side of the neighbourhood the fit's window is pooled over by likeness (0: none).
    pub fn pool_like(&self) -> usize {
        self.pool_like
    }

    /// Candidates `C` of the evidence and candidates pooled per feature channel (0, · for a
    /// network on other inputs).
    pub fn grid(&self) -> (usize, usize) {
        (self.candidates, self.pool)
    }

    /// Candidates per bin of the range fit whose evidence it reads.
    pub fn grid_oversample(&self) -> usize {
        self.oversample
    }

    /// The range (m) at a continuous candidate coordinate `u` (cyclic over `C`), as
    /// [`CandidateGrid::range`].
    pub fn range_of(&self, u: f32) -> f32 {
        CandidateGrid { candidates: self.candidates, oversample: self.oversample, range_m: self.range_m() }.range(u as f64) as f32
    }

    /// The evidence of every frame of a batch, on the CPU (no gradient reaches `y`).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → features `[B, F, H, W]`, skip `[B, S·C, H, W]` (`S` windows)
    pub fn evidence(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>) {
        let (features, skip, _) = self.evidence_frames(y, sensor);
        (features, skip)
    }

    /// [`Self::evidence`] and each frame's noise level.
    pub(crate) fn evidence_frames(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>, Vec<f32>) {
        let [b, m, h, w] = y.dims();
        let device = y.device();
        let v: Vec<f32> = y.into_data().convert::<f32>().try_into_vec::<f32>().unwrap_or_default();
        let templates = RangeTemplates::new(&sensor.matrix, &self.fit_options());
        let sc = self.candidates * SCALES;
        let f = tcsense_fits::depth::range_feature_channels(self.candidates, self.pool);
        let (mut features, mut skip): (Vec<f32>, Vec<f32>) = (Vec::with_capacity(b * f * h * w), Vec::with_capacity(b * sc * h * w));
        let mut noise = Vec::with_capacity(b);
        for i in 0..b {
            let yi = ArrayView3::from_shape((m, h, w), &v[i * m * h * w..(i + 1) * m * h * w]).expect("[M, H, W] frame");
            let e = match templates.costs(&yi) {
                Some(costs) => templates.evidence(&costs, &yi.sum_axis(Axis(0)), self.pool),
                None => tcsense_fits::evidence::Evidence {
                    skip: ndarray::Array3::zeros((h, w, sc)),
                    features: ndarray::Array3::zeros((h, w, f)),
                    noise: 1.0,
                },
            };
            features.extend(e.features.iter());
            skip.extend(e.skip.iter());
            noise.push(e.noise);
        }
        // (the evidence is pixel-major)
        (
            Tensor::<4>::from_data(TensorData::new(features, [b, h, w, f]), &device).permute([0, 3, 1, 2]),
            Tensor::<4>::from_data(TensorData::new(skip, [b, h, w, sc]), &device).permute([0, 3, 1, 2]),
            noise,
        )
    }

    /// [`Self::evidence`] carrying the gradient of the evidence in the taps and in the sensor's
    /// `A` (deep sensing): the fit's values, the gradient of its differentiable copy
    /// ([`crate::range_evidence`]).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → features `[B, F, H, W]`, skip `[B, S·C, H, W]`
    pub fn evidence_with_gradient(&self, y: Tensor<4>, sensor: &SensorTensors) -> (Tensor<4>, Tensor<4>) {
        let b = y.dims()[0];
        let device = y.device();
        let (features, skip, noise) = self.evidence_frames(y.clone().detach(), sensor);
        let nats: Vec<f32> = noise.iter().map(|v| 1.0 / (2.0 * v)).collect();
        let nats = Tensor::<1>::from_data(TensorData::new(nats, [b]), &device);
        let opts = self.fit_options();
        let (post, copy) = range_evidence(y, sensor.a.clone(), sensor.block, self.oversample, nats, opts.fit.window, self.pool);
        with_gradient_of(features, skip, post, copy)
    }

    /// The posterior's logits over the candidates (the windows' log-likelihoods at learned
    /// weights plus the learned log-prior) and the first return's confidence logit.
    ///
    /// # Shapes
    /// - `features`: `[B, F, H, W]`, `skip`: `[B, S·C, H, W]` → `([B, C, H, W], [B, 1, H, W])`
    pub fn posterior(&self, features: Tensor<4>, skip: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
        let o = conv1x1(self.head(), trunk(self.down(), self.up(), features)); // [B, C + S, H, W]
        let c = self.candidates;
        let likelihood = windowed_likelihood(&o, skip, c, SCALES - 1);
        let prior = (o.clone().narrow(1, 0, c).div_scalar(PRIOR_BOUND)).tanh().mul_scalar(PRIOR_BOUND);
        (likelihood + prior, o.narrow(1, c, 1))
    }

    /// `[B, 2K, H, W]` from the posterior's modes, without the tap domain (the second return,
    /// which is the fit's, absent).
    pub(crate) fn predict_on_evidence(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        let (features, skip) = self.evidence(y, sensor);
        let (logits, confidence) = self.posterior(features, skip);
        self.depth_channels(logits, confidence)
    }

    /// The depth channels `[B, 2K, H, W]` of the modes of `logits` `[B, C, H, W]` with the
    /// first return's `confidence` `[B, 1, H, W]`.
    fn depth_channels(&self, logits: Tensor<4>, confidence: Tensor<4>) -> Tensor<4> {
        let [b, c, h, w] = logits.dims();
        let device = logits.device();
        let v: Vec<f32> = logits.into_data().try_into_vec().unwrap_or_default();
        let k = self.returns();
        let mut depth = vec![0f32; b * k * h * w];
        for i in 0..b {
            let u = cyclic_modes(&v[i * c * h * w..(i + 1) * c * h * w], c);
            for (p, &u) in u.iter().enumerate() {
                depth[i * k * h * w + p] = if u.is_finite() { self.range_of(u) } else { 0.0 };
            }
        }
        let depth = Tensor::<4>::from_data(TensorData::new(depth, [b, k, h, w]), &device);
        let mut conf = vec![confidence];
        if k > 1 {
            conf.push(Tensor::<4>::full([b, k - 1, h, w], ABSENT, &device));
        }
        Tensor::cat(vec![depth, Tensor::cat(conf, 1)], 1)
    }

    /// What the loss sees: [`Self::depth_channels`] and the log-posterior over the
    /// candidates, `[B, 2K + C, H, W]`.
    pub(crate) fn train_on_evidence(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        let (features, skip) = if sensor.differentiable { self.evidence_with_gradient(y, sensor) } else { self.evidence(y, sensor) };
        let (logits, confidence) = self.posterior(features, skip);
        let depth = self.depth_channels(logits.clone().detach(), confidence);
        Tensor::cat(vec![depth, log_softmax(logits, 1)], 1)
    }

    /// The decoder's product, frame by frame: the evidence, the posterior, its modes, the fit's
    /// steps 3 and 4 seeded by them ([`RangeTemplates::ranges`] with [`Seeds::Modes`]).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, 2K, H, W]` (m in arrival order, NaN where none; confidence logits)
    pub(crate) fn decode_on_evidence(&self, y: &ArrayView4<'_, f32>, sensor: &SensorTensors) -> Array4<f32> {
        let (b, _, h, w) = y.dim();
        let k = self.returns();
        let device = sensor.lambda.device();
        let mut templates = RangeTemplates::new(&sensor.matrix, &self.fit_options());
        let mut out = Array4::<f32>::from_elem((b, 2 * k, h, w), f32::NAN);
        let c = self.candidates;
        for i in 0..b {
            let yi = y.index_axis(Axis(0), i);
            let Some(costs) = templates.costs(&yi) else {
                out.index_axis_mut(Axis(0), i).slice_mut(ndarray::s![k.., .., ..]).fill(ABSENT);
                continue;
            };
            let e = templates.evidence(&costs, &yi.sum_axis(Axis(0)), self.pool);
            let tensor = |a: ndarray::Array3<f32>| {
                let (h, w, c) = a.dim();
                Tensor::<4>::from_data(TensorData::new(a.into_raw_vec_and_offset().0, [1, h, w, c]), &device).permute([0, 3, 1, 2])
            };
            let (logits, confidence) = self.posterior(tensor(e.features), tensor(e.skip));
            let logits: Vec<f32> = logits.into_data().try_into_vec().unwrap_or_default();
            let conf: Vec<f32> = confidence.into_data().try_into_vec().unwrap_or_default();
            let u = cyclic_modes(&logits, c);
            let ranges = templates.ranges(&costs, Seeds::Modes(&u));
            let mut o = out.index_axis_mut(Axis(0), i);
            for p in 0..h * w {
                let (r, q) = (p / w, p % w);
                for j in 0..k.min(ranges.dim().0) {
                    o[(j, r, q)] = ranges[(j, r, q)];
                }
                // a return's confidence is the first's where it has a range (none: an unlit pixel,
                // or no second return)
                for j in 0..k {
                    o[(k + j, r, q)] = if ranges[(j, r, q)].is_finite() { conf[p] } else { ABSENT };
                }
            }
        }
        out
    }
}

/// The mode of every pixel's posterior over `c` cyclic candidates, refined by the parabola
/// through its log at the two neighbours (within ½; none where a neighbour ties with it or a
/// value is not finite). NaN where every logit is equal (an unlit pixel: no evidence, no prior).
///
/// # Shapes
/// - `logits`: `[C, H·W]` (candidate-major) → `[H·W]` (candidate coordinates in `[0, C)`)
pub fn cyclic_modes(logits: &[f32], c: usize) -> Vec<f32> {
    let hw = logits.len() / c.max(1);
    (0..hw)
        .map(|p| {
            let at = |k: usize| logits[(k % c) * hw + p];
            let (mut best, mut lo, mut hi) = (0usize, f32::INFINITY, f32::NEG_INFINITY);
            for k in 0..c {
                let v = at(k);
                lo = lo.min(v);
                if v > hi {
                    (hi, best) = (v, k);
                }
            }
            if !(hi > lo) {
                return f32::NAN;
            }
            let (l, m, r) = (at(best + c - 1), hi, at(best + 1));
            let curv = l + r - 2.0 * m;
            let delta = if l < m && r < m && curv < 0.0 { (0.5 * (l - r) / curv).clamp(-0.5, 0.5) } else { 0.0 };
            (best as f32 + delta).rem_euclid(c as f32)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::Network;
    use crate::{UnetConfig, UnetHead, UnetInput};
    use burn::tensor::Device;
    use tcsense_fits::depth::fit_ranges;
    use tcsense_sensor::{Codes, Irf, MeasurementMatrix, SensorParams};

    /// The zoo's codes designed for range (4 taps, 2×2, L = 32, alias 0.77), physical IRF.
    fn sensor() -> MeasurementMatrix {
        let codes = Codes::from_json(include_str!("../../zoo/unet-lidar-designed/codes.json")).unwrap();
        let params = SensorParams { irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, ..SensorParams::from_codes(&codes) };
        MeasurementMatrix::synthesize(&codes, &params.validate().unwrap()).unwrap()
    }

    /// Untrained (a zero log-prior), the network on the range fit's evidence is the fit: on
    /// clean taps of a scene with two surfaces and a sheet in front of one, its first return
    /// is the fit's to 0.02 bins and the truth's to 0.05, its second returns are the fit's,
    /// and training sees the log-posterior over the candidates.
    #[test]
    fn on_the_range_fit_evidence_an_untrained_network_is_the_fit() {
        let device = Device::flex();
        let a = sensor();
        let (h, w, t) = (16, 16, a.bins());
        let range = tcsense_sensor::C * a.bin_width_s() / 2.0 * t as f64;
        let dz = range / t as f64;
        // returns (bins, amplitude): a wall at 19.7 on the left with a sheet at 6.4 in its top
        // half, a wall at 27.3 on the right, ambient 0.01
        let returns = |i: usize, j: usize| -> Vec<(f64, f64)> {
            match (i < 8, j < 8) {
                (true, true) => vec![(6.4, 0.4), (19.7, 1.0)],
                (false, true) => vec![(19.7, 1.0)],
                _ => vec![(27.3, 0.8)],
            }
        };
        let mut x = vec![0.01f32; t * h * w];
        for i in 0..h {
            for j in 0..w {
                for (tau, amp) in returns(i, j) {
                    let p = tau - 0.5;
                    let t0 = p.floor() as usize;
                    x[(t0 % t) * h * w + i * w + j] += (amp * (1.0 - (p - p.floor()))) as f32;
                    x[((t0 + 1) % t) * h * w + i * w + j] += (amp * (p - p.floor())) as f32;
                }
            }
        }
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let y = st.forward(Tensor::<4>::from_data(TensorData::new(x, [1, t, h, w]), &device));
        let cfg =
            UnetConfig::new(4, t, range).with_base_width(4).with_levels(2).with_head(UnetHead::ScoreVolume).with_input(UnetInput::Costs);
        assert!(cfg.validate().is_ok() && cfg.clone().with_pool(0).validate().is_err());
        assert!(cfg.clone().with_head(UnetHead::Regression).validate().is_err());
        let net = cfg.init(&device);
        let yv: Vec<f32> = y.clone().into_data().try_into_vec().unwrap();
        let ya = Array4::from_shape_vec((1, 4, h, w), yv).unwrap();
        let got = net.decode_frames(&ya.view(), &st).expect("the evidence's product");
        assert_eq!(got.dim(), (1, 4, h, w));
        let fit = fit_ranges(&ya.index_axis(Axis(0), 0), &a, &net.fit_options());
        let bins = |v: f32| v as f64 / dz;
        let (mut same_second, mut seconds) = (0, 0);
        for i in 0..h {
            for j in 0..w {
                if (6..=9).contains(&j) || (6..=9).contains(&i) {
                    continue; // windows across an edge
                }
                let (first, second) = (got[(0, 0, i, j)], got[(0, 1, i, j)]);
                assert!(
                    (bins(first) - bins(fit[(0, i, j)])).abs() < 0.02,
                    "({i}, {j}): {} against the fit's {}",
                    bins(first),
                    bins(fit[(0, i, j)])
                );
                let want = returns(i, j)[0].0;
                assert!((bins(first) - want).abs() < 0.25, "({i}, {j}): {} against {want}", bins(first));
                if returns(i, j).len() == 1 {
                    assert!((bins(first) - want).abs() < 0.05, "({i}, {j}): {} against {want}", bins(first));
                }
                seconds += fit[(1, i, j)].is_finite() as usize;
                same_second += (fit[(1, i, j)].is_finite() == second.is_finite()
                    && (!second.is_finite() || (bins(second) - bins(fit[(1, i, j)])).abs() < 0.02)) as usize;
                // the untrained confidence is 0.5: a return
                assert_eq!(got[(0, 2, i, j)], 0.0);
            }
        }
        assert!(seconds >= 20, "the fit finds the sheet's second returns ({seconds})");
        assert_eq!(same_second, 144, "second returns as the fit's");
        let train = net.train_output(y, &st);
        assert_eq!(train.dims(), [1, 4 + cfg.candidates(), h, w]);
        let total: Vec<f32> = train.narrow(1, 4, cfg.candidates()).exp().sum_dim(1).into_data().try_into_vec().unwrap();
        assert!(total.iter().all(|v| (v - 1.0).abs() < 1e-4), "a posterior sums to 1");
    }

    /// Pooled by likeness (`pool_like`), the untrained network is `depth-fit-pooled`: on a
    /// dim frame of two walls its first returns are that fit's, nearer the truth than the
    /// network on the window alone; the setting is checked.
    #[test]
    fn pooled_by_likeness_the_untrained_network_is_the_pooled_fit() {
        let device = Device::flex();
        let a = sensor();
        let (h, w, t) = (16, 24, a.bins());
        let range = tcsense_sensor::C * a.bin_width_s() / 2.0 * t as f64;
        let dz = range / t as f64;
        let tau = |j: usize| -> f64 {
            if j < w / 2 {
                9.3
            } else {
                21.7
            }
        };
        let mut x = vec![0.05f32; t * h * w];
        for i in 0..h {
            for j in 0..w {
                let p = tau(j) - 0.5;
                let t0 = p.floor() as usize;
                x[t0 * h * w + i * w + j] += (1.0 - (p - p.floor())) as f32;
                x[(t0 + 1) * h * w + i * w + j] += (p - p.floor()) as f32;
            }
        }
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let clean: Vec<f32> =
            st.forward(Tensor::<4>::from_data(TensorData::new(x, [1, t, h, w]), &device)).into_data().try_into_vec().unwrap();
        // about four photons a pixel: shot noise from a splitmix64 stream (twelve uniforms)
        let per_pixel: f32 = clean.iter().sum::<f32>() / (h * w) as f32;
        let scale = 4.0 / per_pixel;
        let mut state = 11u64;
        let mut uniform = move || {
            state = state.wrapping_add(0x9E3779B97F4A7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
            ((z ^ (z >> 31)) >> 11) as f32 / (1u64 << 53) as f32
        };
        let y: Vec<f32> = clean
            .iter()
            .map(|&v| {
                let e = v * scale;
                let n: f32 = (0..12).map(|_| uniform()).sum::<f32>() - 6.0;
                (e + e.sqrt() * n).max(0.0)
            })
            .collect();
        let ya = Array4::from_shape_vec((1, 4, h, w), y).unwrap();
        let cfg =
            UnetConfig::new(4, t, range).with_base_width(4).with_levels(2).with_head(UnetHead::ScoreVolume).with_input(UnetInput::Costs);
        for bad in [3, 4, 11, 65] {
            assert!(cfg.clone().with_pool_like(bad).validate().is_err(), "{bad}");
        }
        assert!(cfg.clone().with_input(UnetInput::Matched).with_pool_like(15).validate().is_err());
        let (plain, pooled) = (cfg.init(&device), cfg.clone().with_pool_like(15).init(&device));
        assert_eq!((plain.pool_like(), pooled.pool_like()), (0, 15));
        let fit = fit_ranges(&ya.index_axis(Axis(0), 0), &a, &pooled.fit_options());
        let first = |net: &crate::Unet| net.decode_frames(&ya.view(), &st).expect("the evidence's product");
        let (p0, p1) = (first(&plain), first(&pooled));
        let (mut same, mut e0, mut e1) = (0, Vec::new(), Vec::new());
        for i in 0..h {
            for j in 0..w {
                let (u, v, f) = (p0[(0, 0, i, j)] as f64 / dz, p1[(0, 0, i, j)] as f64 / dz, fit[(0, i, j)] as f64 / dz);
                same += ((v - f).abs() < 0.05) as usize;
                let err = |r: f64| if r.is_finite() { (r - tau(j)).abs() } else { f64::INFINITY };
                e0.push(err(u));
                e1.push(err(v));
            }
        }
        assert!(same * 10 >= 9 * h * w, "the pooled network's first return is the pooled fit's on {same} of {} pixels", h * w);
        let median = |mut e: Vec<f64>| {
            e.sort_by(f64::total_cmp);
            e[e.len() / 2]
        };
        let (m0, m1) = (median(e0), median(e1));
        assert!(m1 < 0.8 * m0, "dim light: pooled {m1} bins against the window's {m0}");
    }

    #[test]
    fn the_cyclic_mode_wraps_and_refines() {
        // 8 candidates, 3 pixels: a quadratic peak at 2.3; a peak at 7.6 across the wrap; flat
        let c = 8;
        let mut v = vec![0f32; c * 3];
        for k in 0..c {
            v[k * 3] = -((k as f32 - 2.3).powi(2));
            let d = ((k as f32 - 7.6 + 4.0).rem_euclid(8.0)) - 4.0;
            v[k * 3 + 1] = -d * d;
        }
        let u = cyclic_modes(&v, c);
        assert!((u[0] - 2.3).abs() < 1e-5, "{u:?}");
        assert!((u[1] - 7.6).abs() < 1e-5, "{u:?}");
        assert!(u[2].is_nan());
    }
}
