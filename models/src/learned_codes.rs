//! Learnable exposure codes (deep sensing, the paper's §III-B-2; DESIGN §6).
//!
//! Logits `θ [N, C, L]` per subpixel `n`, choice `c` and mask `l` — with the tap constraint
//! `C = M` (+1 for the drain, last) and a softmax over the choices; without it `C = M`
//! independent bits through a sigmoid. The relaxed bits (temperature `τ`) feed the
//! measurement matrix through the sensor's code basis `G [L, T]`
//! ([`tcsense_sensor::MeasurementMatrix::code_basis`]): `A(θ)[n][m][·] = Σ_l b[n][m][l]·G[l][·]`,
//! the same IRF, oversampling and heterodyne model as the sensor crate, linear in the bits.
//!
//! Relaxation: a softmax (or sigmoid) with a falling temperature and a straight-through
//! estimator (Bengio et al. 2013): the forward pass uses the hard one-hot (or thresholded)
//! bits, so the measurements and the decoder see real codes, and the gradient is that of the
//! soft bits. Penalties on the soft bits push toward the Hamming and window constraints;
//! [`tcsense_sensor::project`] makes them exact at the end.

use burn::module::{Module, Param};
use burn::tensor::activation::{sigmoid, softmax};
use burn::tensor::{Device, Tensor, TensorData};
use ndarray::Array3;
use tcsense_sensor::{Codes, Constraints};

/// Learnable code logits.
#[derive(Module, Debug)]
pub struct CodeLogits {
    /// `θ [N, C, L]`.
    pub theta: Param<Tensor<3>>,
}

/// What the logits mean: the tap constraint (softmax over taps + drain) or independent bits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CodeRelaxation {
    pub taps: usize,
    /// Softmax over the taps (and drain) instead of independent sigmoids.
    pub tap: bool,
    pub drain: bool,
}

impl CodeRelaxation {
    /// Choices per subpixel `C`.
    pub fn choices(&self) -> usize {
        self.taps + usize::from(self.tap && self.drain)
    }

    pub fn of(codes: &Codes, constraints: &Constraints) -> Self {
        CodeRelaxation { taps: codes.taps(), tap: constraints.tap, drain: codes.drain() }
    }
}

impl CodeLogits {
    /// Logits that start at `codes`: `+margin` on the bits that are on (the tap that is on,
    /// or the drain), `−margin` elsewhere.
    ///
    /// # Shapes
    /// - `θ`: `[N, C, L]`
    pub fn from_codes(codes: &Codes, relax: &CodeRelaxation, margin: f32, device: &Device) -> Self {
        let (n, m, l) = (codes.subpixels(), codes.taps(), codes.length());
        let c = relax.choices();
        let theta = Array3::from_shape_fn((n, c, l), |(n, c, l)| {
            let on = if c < m { codes.get(n, c, l) } else { (0..m).all(|k| !codes.get(n, k, l)) };
            if on {
                margin
            } else {
                -margin
            }
        });
        CodeLogits::from_array(&theta, device)
    }

    /// Wrap logits `[N, C, L]`.
    pub fn from_array(theta: &Array3<f32>, device: &Device) -> Self {
        let shape = theta.shape().to_vec();
        let data = TensorData::new(theta.iter().copied().collect::<Vec<f32>>(), [shape[0], shape[1], shape[2]]);
        CodeLogits { theta: Param::from_tensor(Tensor::from_data(data, device)) }
    }

    /// The logits as an array `[N, C, L]` (for the projection).
    pub fn to_array(&self) -> Array3<f32> {
        let t = self.theta.val();
        let [n, c, l] = t.dims();
        Array3::from_shape_vec((n, c, l), t.into_data().try_into_vec::<f32>().expect("f32 logits")).expect("N·C·L values")
    }

    /// The relaxed code bits at temperature `tau`: soft, or hard in the forward pass with the
    /// soft gradient (`straight_through`).
    ///
    /// # Shapes
    /// - returns: `[N, M, L]`, values in `[0, 1]`
    pub fn bits(&self, relax: &CodeRelaxation, tau: f64, straight_through: bool) -> Tensor<3> {
        let z = self.theta.val().div_scalar(tau);
        let [n, c, l] = z.dims();
        let soft = if relax.tap { softmax(z, 1) } else { sigmoid(z) };
        let probs = if straight_through {
            let hard = if relax.tap {
                let max = soft.clone().max_dim(1).repeat_dim(1, c);
                soft.clone().greater_equal(max).float()
            } else {
                soft.clone().greater_elem(0.5).float()
            };
            hard + soft.clone() - soft.detach()
        } else {
            soft
        };
        // the drain column is no tap
        probs.slice([0..n, 0..relax.taps, 0..l])
    }
}

/// `A(θ) = bits · G`: the measurement matrix of (relaxed) code bits.
///
/// # Shapes
/// - `bits`: `[N, M, L]`, `basis`: `[L, T]` → `[N, M, T]`
pub fn matrix(bits: Tensor<3>, basis: Tensor<2>) -> Tensor<3> {
    let [n, m, l] = bits.dims();
    let t = basis.dims()[1];
    bits.reshape([n * m, l]).matmul(basis).reshape([n, m, t])
}

/// `y = A x` per pixel in plain tensor operations (differentiable in `A` and `x`; the fused
/// kernels of `tcsense-kernels` take `A` as data): subpixel `n = (h mod bh)·bw + (w mod bw)`.
///
/// # Shapes
/// - `a`: `[N, M, T]`, `x`: `[B, T, H, W]` → `[B, M, H, W]`
pub fn forward(a: Tensor<3>, x: Tensor<4>, block: (usize, usize)) -> Tensor<4> {
    let (bh, bw) = block;
    let [b, t, h, w] = x.dims();
    let m = a.dims()[1];
    let (hb, wb) = (h / bh, w / bw);
    let xb: Tensor<3> = x.reshape([b, t, hb, bh, wb, bw]).permute([3, 5, 0, 2, 4, 1]).reshape([bh * bw, b * hb * wb, t]);
    let y = xb.matmul(a.swap_dims(1, 2)); // [N, B·P, M]
    y.reshape([bh, bw, b, hb, wb, m]).permute([2, 5, 3, 0, 4, 1]).reshape([b, m, h, w])
}

/// The hard codes of logits `[N, C, L]`: the best choice per subpixel and mask (the drain
/// turns every tap off), or every bit whose logit is positive; no constraints declared (they
/// may break them: that is what the projection is for).
pub fn hard_codes(theta: &Array3<f32>, relax: &CodeRelaxation, like: &Codes) -> tcsense_sensor::Result<Codes> {
    let mut codes = Codes::zeros(like.shape(), like.clock_hz, Constraints::default())?;
    let (n_sub, c, len) = theta.dim();
    for n in 0..n_sub {
        for l in 0..len {
            if relax.tap {
                let best = (0..c).fold(0, |b, k| if theta[(n, k, l)] > theta[(n, b, l)] { k } else { b });
                if best < relax.taps {
                    codes.set(n, best, l, true);
                }
            } else {
                for m in 0..relax.taps {
                    codes.set(n, m, l, theta[(n, m, l)] > 0.0);
                }
            }
        }
    }
    Ok(codes)
}

/// The code basis `G [L, T]` as a tensor.
pub fn basis_tensor(g: &ndarray::Array2<f32>, device: &Device) -> Tensor<2> {
    let (l, t) = g.dim();
    Tensor::from_data(TensorData::new(g.iter().copied().collect::<Vec<f32>>(), [l, t]), device)
}

/// Soft bit changes from each mask to the next (cyclic), summed over the block's channels.
///
/// # Shapes
/// - `bits`: `[N, M, L]` → `[L]`
fn changes(bits: Tensor<3>) -> Tensor<1> {
    let [n, m, l] = bits.dims();
    let next = bits.clone().roll_dim(-1, 2);
    (next - bits).abs().reshape([n * m, l]).sum_dim(0).reshape([l])
}

/// Penalty toward the Hamming constraint: `Σ_l relu(changes_l − H)²`, zero on codes that
/// meet it.
///
/// # Shapes
/// - `bits`: `[N, M, L]` → `[1]`
pub fn hamming_penalty(bits: Tensor<3>, h: usize) -> Tensor<1> {
    let over = changes(bits).sub_scalar(h as f32).clamp_min(0.0);
    over.clone().mul(over).sum()
}

/// Penalty toward the window constraint: for every channel, the products of soft changes
/// `W − 1` or fewer masks apart (`Σ_l Σ_{k<W} c_l·c_{l+k}`, cyclic) — on binary codes the
/// number of runs shorter than `W`, zero on codes that meet it.
///
/// # Shapes
/// - `bits`: `[N, M, L]` → `[1]`
pub fn window_penalty(bits: Tensor<3>, w: usize) -> Tensor<1> {
    let c = (bits.clone() - bits.roll_dim(1, 2)).abs(); // change into mask l
    let mut total = c.clone().sum().mul_scalar(0.0);
    for k in 1..w {
        total = total + (c.clone() * c.clone().roll_dim(-(k as i64), 2)).sum();
    }
    total
}

/// The identifiability term of deep sensing: a squared hinge on the range alias
/// ([`tcsense_sensor::identify`]), `Σ relu(δ − ‖ĝ_i − ĝ_j‖)²` over every pair of bins at least
/// `min_shift` apart (cyclic), where `ĝ_t` is the unit block signature of a return in bin `t`
/// (column `t` of `A`, all `N·M` taps). Zero on codes whose alias is `δ` or more; otherwise it
/// pushes apart exactly the pairs of ranges the taps confuse, which a loss over typical scenes
/// hardly sees.
///
/// # Shapes
/// - `a`: `[N, M, T]` → `[1]`
pub fn alias_penalty(a: Tensor<3>, min_shift: usize, threshold: f32) -> Tensor<1> {
    let [n, m, t] = a.dims();
    let device = a.device();
    let s = a.reshape([n * m, t]).swap_dims(0, 1); // [T, N·M]
    let norm = (s.clone() * s.clone()).sum_dim(1).add_scalar(1e-12).sqrt(); // [T, 1]
    let u = s / norm;
    let gram = u.clone().matmul(u.swap_dims(0, 1)); // [T, T]
    let dist = gram.mul_scalar(-2.0).add_scalar(2.0).clamp_min(0.0).add_scalar(1e-12).sqrt();
    let mask: Vec<f32> = (0..t * t)
        .map(|k| {
            let (i, j) = (k / t, k % t);
            let gap = (i + t - j) % t;
            if gap.min(t - gap) >= min_shift && i < j {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let mask = Tensor::<2>::from_data(TensorData::new(mask, [t, t]), &device);
    let hinge = (dist.neg().add_scalar(threshold)).clamp_min(0.0) * mask;
    (hinge.clone() * hinge).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::codes::CodeShape;
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::params::SensorParams;
    use tcsense_sensor::{Irf, MeasurementMatrix, Sampling};

    fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    /// At hard codes the straight-through `A(θ)` is the sensor's matrix of those codes: ideal
    /// and physical IRF, oversampling and heterodyne, with and without drain.
    #[test]
    fn matrix_at_hard_codes_equals_the_sensor() {
        let device = Device::flex();
        let phys = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
        for (drain, constraints) in [
            (false, Constraints { tap: true, hamming: Some(2), window: Some(2) }),
            (true, Constraints { tap: true, hamming: None, window: Some(2) }),
            (false, Constraints { tap: false, hamming: None, window: None }),
        ] {
            let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain };
            let codes = random_codes(shape, 607e6, constraints, 3).unwrap();
            let relax = CodeRelaxation::of(&codes, &constraints);
            let logits = CodeLogits::from_codes(&codes, &relax, 4.0, &device);
            for (sampling, irf) in [
                (Sampling::Oversample(1), Irf::Ideal),
                (Sampling::Oversample(2), phys),
                (Sampling::Heterodyne(4), Irf::Ideal),
                (Sampling::Heterodyne(4), phys),
            ] {
                let spec = SensorParams { sampling, irf, ..SensorParams::from_codes(&codes) }.validate().unwrap();
                let want = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
                let g = basis_tensor(&MeasurementMatrix::code_basis(&spec), &device);
                let got = to_vec(matrix(logits.bits(&relax, 0.5, true), g));
                let peak = want.a().iter().fold(0f32, |m, v| m.max(v.abs()));
                for (a, b) in want.a().iter().zip(&got) {
                    assert!((a - b).abs() <= 1e-5 * peak, "{} {sampling:?} {irf:?}: {a} vs {b}", constraints.label());
                }
            }
        }
    }

    /// The identifiability term is the closed-form alias's hinge: zero on codes whose alias
    /// is above the threshold, positive on the prototype's seed-1 codes (bins 9 and 22 at
    /// 0.011), and its gradient through the relaxed bits lowers it.
    #[test]
    fn alias_penalty_sees_the_alias_and_its_gradient_removes_it() {
        let device = Device::flex().autodiff();
        let phys = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
        let codes = tcsense_sensor::generate::prototype_codes(1).unwrap();
        let spec = SensorParams { irf: phys, ..SensorParams::from_codes(&codes) }.validate().unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let alias = tcsense_sensor::identify::range_alias(&tcsense_sensor::identify::Columns::new(&a, 1));
        let at = |thr: f32| {
            let t = Tensor::<3>::from_data(TensorData::new(a.a().iter().copied().collect::<Vec<f32>>(), [4, 4, 32]), &device);
            to_vec(alias_penalty(t, 2, thr))[0]
        };
        assert_eq!(at(alias.distance as f32 * 0.999), 0.0, "no pair below the alias itself");
        let p = at(0.5);
        assert!(p >= (0.5 - alias.distance as f32).powi(2), "at least the closest pair's hinge: {p}");
        // a small gradient step on the logits lowers it
        let relax = CodeRelaxation::of(&codes, &codes.constraints);
        let logits = CodeLogits::from_codes(&codes, &relax, 0.1, &device);
        let g = basis_tensor(&MeasurementMatrix::code_basis(&spec), &device);
        let value = |theta: Tensor<3>| {
            alias_penalty(matrix(CodeLogits { theta: Param::from_tensor(theta) }.bits(&relax, 1.0, false), g.clone()), 2, 0.5)
        };
        let theta = logits.theta.val().require_grad();
        let loss = value(theta.clone());
        let before = to_vec(loss.clone())[0];
        let grad = theta.grad(&loss.backward()).expect("gradient");
        let stepped =
            Array3::from_shape_vec((4, 4, 32), logits.to_array().iter().zip(to_vec(grad)).map(|(t, g)| t - 0.05 * g).collect()).unwrap();
        let after = to_vec(value(CodeLogits::from_array(&stepped, &device).theta.val()))[0];
        assert!(after < before, "{after} < {before}");
    }

    /// The tensor forward model equals the sensor's per-pixel operator, and the hard codes of
    /// logits made from codes are those codes.
    #[test]
    fn tensor_forward_equals_the_sensor_and_hard_codes_round_trip() {
        let device = Device::flex();
        let shape = CodeShape { bh: 2, bw: 3, taps: 3, length: 8, drain: true };
        let constraints = Constraints { tap: true, hamming: None, window: Some(2) };
        let codes = random_codes(shape, 607e6, constraints, 4).unwrap();
        let relax = CodeRelaxation::of(&codes, &constraints);
        let logits = CodeLogits::from_codes(&codes, &relax, 2.0, &device);
        assert_eq!(hard_codes(&logits.to_array(), &relax, &codes).unwrap().digest(), codes.digest());
        let spec = SensorParams { sampling: Sampling::Oversample(2), ..SensorParams::from_codes(&codes) }.validate().unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let x = ndarray::Array4::from_shape_fn((2, 16, 4, 6), |(b, t, h, w)| ((b * 5 + t * 3 + h * 7 + w * 11) % 17) as f32);
        let want = a.plan(4, 6).unwrap().forward_batch(&x.view()).unwrap();
        let a_t = Tensor::<3>::from_data(TensorData::new(a.a().iter().copied().collect::<Vec<f32>>(), [6, 3, 16]), &device);
        let got = to_vec(forward(a_t, crate::net::to_tensor(&x.view(), &device), (2, 3)));
        for (u, v) in want.iter().zip(&got) {
            assert!((u - v).abs() <= 1e-4 * u.abs().max(1.0), "{u} vs {v}");
        }
    }

    /// The gradient of a loss of the relaxed `A(θ)` with respect to `θ` matches central
    /// differences.
    #[test]
    fn relaxed_matrix_gradient_matches_finite_differences() {
        let device = Device::flex().autodiff();
        let shape = CodeShape { bh: 1, bw: 2, taps: 3, length: 8, drain: true };
        let constraints = Constraints { tap: true, hamming: Some(2), window: Some(2) };
        let codes = random_codes(shape, 607e6, constraints, 1).unwrap();
        let spec = SensorParams {
            sampling: Sampling::Oversample(2),
            irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            ..SensorParams::from_codes(&codes)
        }
        .validate()
        .unwrap();
        let g = MeasurementMatrix::code_basis(&spec);
        let relax = CodeRelaxation::of(&codes, &constraints);
        let theta0 = Array3::from_shape_fn((2, 4, 8), |(n, c, l)| ((n * 7 + c * 3 + l * 5) % 11) as f32 * 0.3 - 1.5);
        let weights = Array3::from_shape_fn((2, 3, 16), |(n, m, j)| ((n + 2 * m + 3 * j) % 7) as f32 - 3.0);
        let loss = |theta: &Array3<f32>, dev: &Device| -> Tensor<1> {
            let logits = CodeLogits::from_array(theta, dev);
            let a = matrix(logits.bits(&relax, 0.7, false), basis_tensor(&g, dev));
            let w = Tensor::<3>::from_data(TensorData::new(weights.iter().copied().collect::<Vec<f32>>(), [2, 3, 16]), dev);
            let b = logits.bits(&relax, 0.7, false);
            (a * w).sum() + hamming_penalty(b.clone(), 1) + window_penalty(b, 3)
        };
        let logits = CodeLogits::from_array(&theta0, &device);
        let theta_t = logits.theta.val().require_grad();
        let lg = CodeLogits { theta: Param::from_tensor(theta_t.clone()) };
        let a = matrix(lg.bits(&relax, 0.7, false), basis_tensor(&g, &device));
        let w = Tensor::<3>::from_data(TensorData::new(weights.iter().copied().collect::<Vec<f32>>(), [2, 3, 16]), &device);
        let b = lg.bits(&relax, 0.7, false);
        let total = (a * w).sum() + hamming_penalty(b.clone(), 1) + window_penalty(b, 3);
        let grads = total.backward();
        let grad = to_vec(theta_t.grad(&grads).expect("gradient"));
        let plain = Device::flex();
        let eps = 1e-2f32;
        for idx in [(0, 0, 0), (0, 3, 2), (1, 1, 5), (1, 2, 7), (0, 2, 4)] {
            let (mut up, mut down) = (theta0.clone(), theta0.clone());
            up[idx] += eps;
            down[idx] -= eps;
            let f = |t: &Array3<f32>| to_vec(loss(t, &plain))[0] as f64;
            let fd = (f(&up) - f(&down)) / (2.0 * eps as f64);
            let flat = idx.0 * 32 + idx.1 * 8 + idx.2;
            let got = grad[flat] as f64;
            assert!((got - fd).abs() <= 2e-2 * fd.abs().max(1.0), "θ{idx:?}: autodiff {got} vs finite differences {fd}");
        }
    }

    /// The penalties vanish on codes that meet the constraints and count the violations of
    /// binary codes that do not.
    #[test]
    fn penalties_are_zero_on_feasible_codes_and_count_violations() {
        let device = Device::flex();
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        let constraints = Constraints { tap: true, hamming: Some(2), window: Some(2) };
        let codes = random_codes(shape, 607e6, constraints, 9).unwrap();
        let relax = CodeRelaxation::of(&codes, &constraints);
        let bits = CodeLogits::from_codes(&codes, &relax, 4.0, &device).bits(&relax, 0.5, true);
        assert_eq!(to_vec(hamming_penalty(bits.clone(), 2))[0], 0.0);
        assert_eq!(to_vec(window_penalty(bits, 2))[0], 0.0);
        // one tap of one subpixel on for a single mask: runs of length 1 in two channels
        // (the tap that was on and the one switched to), and 4 changed bits at two transitions
        let mut bad = Codes::zeros(shape, 607e6, constraints).unwrap();
        for n in 0..4 {
            for l in 0..16 {
                bad.set(n, 0, l, true);
            }
        }
        bad.set(0, 0, 5, false);
        bad.set(0, 1, 5, true);
        let bits = CodeLogits::from_codes(&bad, &relax, 4.0, &device).bits(&relax, 0.5, true);
        assert_eq!(to_vec(window_penalty(bits.clone(), 2))[0], 2.0);
        assert_eq!(to_vec(hamming_penalty(bits, 2))[0], 0.0);
        let bits = CodeLogits::from_codes(&bad, &relax, 4.0, &device).bits(&relax, 0.5, true);
        assert_eq!(to_vec(hamming_penalty(bits, 1))[0], 2.0, "2 changed bits over H = 1, twice: (2−1)² + (2−1)²");
    }
}
