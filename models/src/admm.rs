//! ADMM-Net (DESIGN §5): `S` unrolled ADMM stages for `min_x ½‖Ax − y‖² + R(x)`.
//!
//! Stage `k` (learned `ρ_k > 0`, step `η_k`, CNN prior `P_k` with `CN` channels):
//!
//! ```text
//! x_k = (AᵀA + ρ_k I)⁻¹ (Aᵀy + ρ_k (z_{k−1} − u_{k−1}))      exact, per pixel (Woodbury)
//! z_k = (x_k + u_{k−1}) + P_k(x_k + u_{k−1})                   residual CNN: 3×3 convs T→CN→CN→T
//! u_k = u_{k−1} + η_k (x_k − z_k)
//! ```
//!
//! starting from the normalised back-projection `z_0 = Aᵀ(AAᵀ + εI)⁻¹y` (the minimum-norm
//! solution of `Ax = y`), `u_0 = 0`; the output is `z_S`. The data-consistency step uses
//! `(ρI + AᵀA)⁻¹ = (I − Aᵀ(ρI_M + AAᵀ)⁻¹A)/ρ`, where `AAᵀ = QΛQᵀ` is decomposed once per
//! subpixel type, so `(ρI_M + AAᵀ)⁻¹ = Q diag(1/(ρ+λ)) Qᵀ` stays differentiable in `ρ`.
//! Time is the channel axis of the convolutions.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::PaddingConfig2d;
use burn::tensor::{activation::relu, Device, Tensor};

use tcsense_kernels::conv_op::conv3x3_layer as conv;

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
}

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
    /// prior's three 3×3 convolutions (`2·9·(T·CN + CN² + CN·T)`).
    pub fn flops(&self, h: usize, w: usize) -> f64 {
        let (t, m, cn) = (self.bins as f64, self.taps as f64, self.channels as f64);
        let per_stage = 4.0 * m * t + 18.0 * (2.0 * t * cn + cn * cn);
        (h * w) as f64 * (4.0 * t * m + self.stages as f64 * per_stage)
    }

    /// Build the network.
    pub fn init(&self, device: &Device) -> AdmmNet {
        let conv = |i: usize, o: usize| Conv2dConfig::new([i, o], [3, 3]).with_padding(PaddingConfig2d::Same).init(device);
        let stages = (0..self.stages)
            .map(|_| Stage {
                conv1: conv(self.bins, self.channels),
                conv2: conv(self.channels, self.channels),
                conv3: conv(self.channels, self.bins),
                log_rho: Param::from_tensor(Tensor::from_floats([self.rho_init.ln() as f32], device)),
                eta: Param::from_tensor(Tensor::from_floats([self.eta_init as f32], device)),
            })
            .collect();
        AdmmNet { stages, normalize: self.normalize }
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
    /// The prior's three 3×3 convolutions `T→CN→CN→T` (weights `[out, in, 3, 3]`).
    pub fn convs(&self) -> [&Conv2d; 3] {
        [&self.conv1, &self.conv2, &self.conv3]
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
}

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
        let aty = sensor.adjoint(y.clone()); // [B, T, H, W]
        let mut z = sensor.pinv(y);
        let mut u = z.zeros_like();
        for st in &self.stages {
            let rho = st.log_rho.val().exp();
            let v = aty.clone() + (z.clone() - u.clone()) * rho.clone().reshape([1, 1, 1, 1]);
            let x = sensor.data_consistency(v, rho);
            let xu = x.clone() + u.clone();
            let h = relu(conv(&st.conv1, xu.clone()));
            let h = relu(conv(&st.conv2, h));
            z = xu + conv(&st.conv3, h);
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
}
