//! ADMM-Net (DESIGN §5): `S` unrolled ADMM stages for `min_x ½‖Ax − y‖² + R(x)`.
//!
//! Stage `k` (learned `ρ_k > 0`, step `η_k`, CNN prior `P_k` with `CN` channels):
//!
//! ```text
//! x_k = (AᵀA + ρ_k I)⁻¹ (Aᵀy + ρ_k (z_{k−1} − u_{k−1}))      exact, per pixel
//! z_k = (x_k + u_{k−1}) + P_k(x_k + u_{k−1})                   residual CNN: 3×3 convs T→CN→CN→T
//! u_k = u_{k−1} + η_k (x_k − z_k)
//! ```
//!
//! starting from the normalised back-projection `z_0 = Aᵀ(AAᵀ + εI)⁻¹y` (the minimum-norm
//! solution of `Ax = y`), `u_0 = 0`; the output is `z_S`. The data-consistency step is
//! computed as `x_k = w + Aᵀ(ρI_M + AAᵀ)⁻¹(y − Aw)`, `w = z_{k−1} − u_{k−1}` (equal by the
//! push-through identity, and free of the `λ/ρ`-fold cancellation of the Woodbury form
//! `(I − Aᵀ(ρI_M + AAᵀ)⁻¹A)/ρ` applied to the right-hand side), where `AAᵀ = QΛQᵀ` is
//! decomposed once per subpixel type, so `(ρI_M + AAᵀ)⁻¹ = Q diag(1/(ρ+λ)) Qᵀ` stays
//! differentiable in `ρ`.
//! The prior comes in two kinds ([`Prior`]). The paper's (`bins`) makes time the channel
//! axis of 3×3 convolutions over the frame: cheap, but each bin has its own weights, so a
//! network trained on decays that start at one delay has learned that delay. The
//! delay-equivariant prior (`delay`) convolves over `(t, y, x)` with `CN` channels per bin:
//! kernels 3×3×3, circular in `t` (the codes loop, so a delay is a cyclic shift of the cube),
//! dilated 1, 3, 9 in `t` in its three layers (every offset of ±13 bins reached exactly once
//! per stage; 1, 3, 9 measured 0.4 dB better than 1, 2, 4 on randomised FLIm). Every bin
//! shares the weights, so delaying the cube by whole bins delays the prior's output the same:
//! `P(roll(x, s)) = roll(P(x), s)`. Each layer is a 3×3 convolution over the frame of the bins
//! `t − d`, `t`, `t + d` as `3·C_in` channels (`tcsense_kernels::delay_op::delay_conv3x3`: on
//! the CPU its im2col reads the three bins in place; elsewhere roll + concatenate + conv).

use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::{activation::relu, Device, Tensor};

use tcsense_kernels::conv_op::conv3x3_layer as conv;
use tcsense_kernels::delay_op::delay_conv3x3_layer;

use crate::net::{Network, Prediction};
use crate::sensor_tensors::SensorTensors;

/// ADMM-Net hyper-parameters.
#[derive(Config, Debug, PartialEq)]
pub struct AdmmNetConfig {
    /// Taps `M` (input channels of the measurements).
    pub taps: usize,
    /// Bins `T` (channels of the cube).
    pub bins: usize,
    /// Unrolled stages `S`.
    #[config(default = 9)]
    pub stages: usize,
    /// CNN channels `CN`.
    #[config(default = 32)]
    pub channels: usize,
    /// Initial `ρ` of every stage.
    #[config(default = 0.1)]
    pub rho_init: f64,
    /// Initial multiplier step `η`.
    #[config(default = 1.0)]
    pub eta_init: f64,
    /// Divide `y` by its mean absolute tap value per frame and multiply the output back, so
    /// the network sees one scale whatever the brightness (`false` in runs written before it
    /// existed).
    #[config(default = false)]
    pub normalize: bool,
    /// The prior's kind (`bins` in runs written before it existed).
    #[config(default = "Prior::Bins")]
    pub prior: Prior,
}

/// What the prior's convolutions run over (see the module documentation).
#[derive(Config, Debug, PartialEq, Eq, Copy)]
pub enum Prior {
    /// 3×3 convolutions over the frame, the `T` bins as channels: `T → CN → CN → T` (the paper's).
    Bins,
    /// 3×3×3 convolutions over `(t, y, x)`, circular in `t` with dilations [`DELAY_DILATIONS`]:
    /// `1 → CN → CN → 1` channels per bin; equivariant to delays of whole bins.
    Delay,
}

/// Dilations in `t` of the delay-equivariant prior's three layers (a cube needs more bins than
/// the largest).
pub const DELAY_DILATIONS: [usize; 3] = [1, 3, 9];

impl AdmmNetConfig {
    /// The paper's LiDAR setting (Table 3): `S = 9`, `CN = 128`.
    pub fn lidar(taps: usize, bins: usize) -> Self {
        AdmmNetConfig::new(taps, bins).with_stages(9).with_channels(128)
    }
    /// The paper's FLIm setting (Table 3): `S = 9`, `CN = 32`.
    pub fn flim(taps: usize, bins: usize) -> Self {
        AdmmNetConfig::new(taps, bins).with_stages(9).with_channels(32)
    }
    /// A CPU default that trains in minutes on two cores: `S = 5`, `CN = 16`.
    pub fn cpu(taps: usize, bins: usize) -> Self {
        AdmmNetConfig::new(taps, bins).with_stages(5).with_channels(16)
    }

    /// Multiply-adds ×2 per frame of `h × w`: `Aᵀy` and the back-projection (`2·2TM` per
    /// pixel), and per stage the data-consistency solve through `M` channels (`2·2MT`) and the
    /// prior's three convolutions: `2·9·(T·CN + CN² + CN·T)` over the frame with bins as
    /// channels, `2·T·27·(CN + CN² + CN)` for the delay prior.
    pub fn flops(&self, h: usize, w: usize) -> f64 {
        let (t, m, cn) = (self.bins as f64, self.taps as f64, self.channels as f64);
        let prior = match self.prior {
            Prior::Bins => 18.0 * (2.0 * t * cn + cn * cn),
            Prior::Delay => 54.0 * t * (2.0 * cn + cn * cn),
        };
        let per_stage = 4.0 * m * t + prior;
        (h * w) as f64 * (4.0 * t * m + self.stages as f64 * per_stage)
    }

    /// Build the network.
    pub fn init(&self, device: &Device) -> AdmmNet {
        let conv = |i: usize, o: usize| Conv2dConfig::new([i, o], [3, 3]).with_padding(PaddingConfig2d::Same).init(device);
        // channels in and out of the prior: the bins (bins prior) or one per bin (delay prior,
        // whose layers see three bins of their input each)
        let (outer, taps) = match self.prior {
            Prior::Bins => (self.bins, 1),
            Prior::Delay => (1, 3),
        };
        let stages = (0..self.stages)
            .map(|_| Stage {
                conv1: conv(taps * outer, self.channels),
                conv2: conv(taps * self.channels, self.channels),
                conv3: conv(taps * self.channels, outer),
                log_rho: Param::from_tensor(Tensor::from_floats([self.rho_init.ln() as f32], device)),
                eta: Param::from_tensor(Tensor::from_floats([self.eta_init as f32], device)),
            })
            .collect();
        AdmmNet { stages, normalize: self.normalize, delay: self.prior == Prior::Delay }
    }
}

/// One ADMM stage.
#[derive(Module, Debug)]
pub struct Stage {
    conv1: Conv2d,
    conv2: Conv2d,
    conv3: Conv2d,
    log_rho: Param<Tensor<1>>,
    eta: Param<Tensor<1>>,
}

impl Stage {
    /// The prior's three 3×3 convolutions (weights `[out, in, 3, 3]`): `T→CN→CN→T` for the
    /// bins prior; for the delay prior `3→CN`, `3·CN→CN`, `3·CN→1`, input channel `j·C_in + c`
    /// being channel `c` at bin `t + (j − 1)·d` (see [`delay_taps`]).
    pub fn convs(&self) -> [&Conv2d; 3] {
        [&self.conv1, &self.conv2, &self.conv3]
    }

    /// The prior's residual `P(x)`.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, T, H, W]`
    fn prior(&self, x: Tensor<4>, kind: Prior) -> Tensor<4> {
        if kind == Prior::Bins {
            let h = relu(conv(&self.conv1, x));
            let h = relu(conv(&self.conv2, h));
            return conv(&self.conv3, h);
        }
        let [b, t, hh, ww] = x.dims();
        // [B, T, C, H, W] → [B, T, C', H, W]: the bins t − d, t, t + d read in place on the CPU
        let layer = |c: &Conv2d, h: Tensor<5>, d: usize| delay_conv3x3_layer(c, h, d);
        let [d1, d2, d3] = DELAY_DILATIONS;
        let h = relu(layer(&self.conv1, x.reshape([b, t, 1, hh, ww]), d1));
        let h = relu(layer(&self.conv2, h, d2));
        layer(&self.conv3, h, d3).reshape([b, t, hh, ww])
    }

    /// `ρ_k = exp(log ρ_k)`.
    pub fn rho(&self) -> f32 {
        self.log_rho.val().exp().into_scalar::<f32>()
    }

    /// The multiplier step `η_k`.
    pub fn eta(&self) -> f32 {
        self.eta.val().into_scalar::<f32>()
    }
}

/// The unrolled network.
#[derive(Module, Debug)]
pub struct AdmmNet {
    stages: Vec<Stage>,
    normalize: bool,
    /// The delay-equivariant prior ([`Prior::Delay`]).
    delay: bool,
}

pub use tcsense_kernels::delay_op::delay_taps;

impl AdmmNet {
    /// Reconstruct cubes from measurements.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn forward(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        if self.normalize {
            // per-frame scale: the mean absolute tap value, [B, 1, 1, 1]
            let s = y.clone().abs().mean_dim(1).mean_dim(2).mean_dim(3) + 1e-12;
            return self.unrolled(y / s.clone(), sensor) * s;
        }
        self.unrolled(y, sensor)
    }

    /// The unrolled stages on `y` as given.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    fn unrolled(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        let mut z = sensor.pinv(y.clone()); // [B, T, H, W]
        let mut u = z.zeros_like();
        for st in &self.stages {
            let rho = st.log_rho.val().exp();
            // (AᵀA + ρI)⁻¹(Aᵀy + ρ(z − u)) without the cancellation of forming Aᵀy + ρ(z − u)
            let x = sensor.x_update(z.clone() - u.clone(), y.clone(), rho);
            let xu = x.clone() + u.clone();
            z = xu.clone() + st.prior(xu, self.prior());
            u = u + (x - z.clone()) * st.eta.val().reshape([1, 1, 1, 1]);
        }
        z
    }

    /// The unrolled stages, in order (for exporters).
    pub fn stages(&self) -> &[Stage] {
        &self.stages
    }

    /// Whether the input is normalised per frame (see [`AdmmNetConfig::normalize`]).
    pub fn normalize(&self) -> bool {
        self.normalize
    }

    /// The prior's kind.
    pub fn prior(&self) -> Prior {
        if self.delay {
            Prior::Delay
        } else {
            Prior::Bins
        }
    }

    /// Learned `ρ` per stage.
    pub fn rhos(&self) -> Vec<f32> {
        self.stages.iter().map(|s| s.log_rho.val().exp().into_scalar::<f32>()).collect()
    }
}

impl Network for AdmmNet {
    const PREDICTION: Prediction = Prediction::Cube;

    fn predict(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        self.forward(y, sensor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Distribution;
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::{MeasurementMatrix, SensorParams};

    #[test]
    fn a_normalised_net_is_scale_equivariant() {
        let device = Device::flex();
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap();
        let st = SensorTensors::new(&a, 8, 8, &device).unwrap();
        let y = Tensor::<4>::random([2, 4, 8, 8], Distribution::Uniform(0.0, 1.0), &device);
        for normalize in [false, true] {
            let net = AdmmNetConfig::new(4, 8).with_stages(2).with_channels(4).with_normalize(normalize).init(&device);
            let (x1, x10) = (net.forward(y.clone(), &st), net.forward(y.clone() * 10.0, &st));
            let rel = ((x10 - x1.clone() * 10.0).abs().max() / (x1.abs().max() * 10.0)).into_scalar::<f32>();
            if normalize {
                assert!(rel < 1e-5, "10·y gives 10·x̂ within {rel}");
            } else {
                assert!(rel > 1e-4, "the biases of the prior break equivariance without the normalisation ({rel})");
            }
        }
    }

    #[test]
    fn delay_taps_stack_the_neighbouring_bins_circularly() {
        let device = Device::flex();
        let (t, c, d) = (6, 2, 2);
        // value of channel c at bin t: 10·t + c
        let v: Vec<f32> = (0..t).flat_map(|ti| (0..c).map(move |ci| (10 * ti + ci) as f32)).collect();
        let h = Tensor::<1>::from_floats(v.as_slice(), &device).reshape([1, t, c, 1, 1]);
        let taps: Vec<f32> = delay_taps(h, d).into_data().try_into_vec::<f32>().unwrap();
        for ti in 0..t {
            for j in 0..3 {
                for ci in 0..c {
                    let src = (ti + t + j * d - d) % t;
                    assert_eq!(taps[ti * 3 * c + j * c + ci], (10 * src + ci) as f32, "bin {ti}, tap {j}, channel {ci}");
                }
            }
        }
    }

    #[test]
    fn the_delay_prior_commutes_with_delays_and_the_bins_prior_does_not() {
        let device = Device::flex();
        let x = Tensor::<4>::random([2, 16, 6, 5], Distribution::Uniform(0.0, 1.0), &device);
        for prior in [Prior::Delay, Prior::Bins] {
            let net = AdmmNetConfig::new(4, 16).with_stages(1).with_channels(4).with_prior(prior).init(&device);
            assert_eq!(net.prior(), prior);
            let p = |x: Tensor<4>| net.stages()[0].prior(x, prior);
            let base = p(x.clone());
            let scale = base.clone().abs().max().into_scalar::<f32>();
            assert!(scale > 1e-3, "the prior is not zero ({scale})");
            for s in [1i64, 5, -3] {
                let rolled = p(x.clone().roll_dim(s, 1));
                let err = (rolled - base.clone().roll_dim(s, 1)).abs().max().into_scalar::<f32>() / scale;
                if prior == Prior::Delay {
                    assert!(err < 1e-5, "P(roll(x, {s})) = roll(P(x), {s}) within {err}");
                } else {
                    assert!(err > 1e-2, "the bins prior has per-bin weights ({err})");
                }
            }
        }
    }
}
