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
use burn::tensor::{activation::relu, Device, Tensor, TensorData};
use tcsense_sensor::MeasurementMatrix;

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
        AdmmNet { stages }
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

/// The unrolled network.
#[derive(Module, Debug)]
pub struct AdmmNet {
    stages: Vec<Stage>,
}

/// The sensor model as tensors for one frame size: `A` per pixel and the eigen-decomposition
/// of `AAᵀ` per pixel.
#[derive(Debug, Clone)]
pub struct SensorTensors {
    /// `[1, M, T, H, W]`
    pub a: Tensor<5>,
    /// Eigenvectors `[1, M(j), M(i), H, W]` (`Q[j][i]`: component `j` of vector `i`).
    pub q: Tensor<5>,
    /// Eigenvalues `[1, M, H, W]`.
    pub lambda: Tensor<4>,
    pub taps: usize,
    pub bins: usize,
    pub height: usize,
    pub width: usize,
}

/// Eigen-decomposition of a symmetric `n × n` matrix (row-major) by cyclic Jacobi rotations:
/// returns `(eigenvalues, Q)` with `Q[j][i]` the `j`-th component of eigenvector `i`.
pub fn jacobi_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = a.to_vec();
    let mut q = vec![0.0; n * n];
    for i in 0..n {
        q[i * n + i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..n).flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j))).map(|(i, j)| m[i * n + j].powi(2)).sum();
        let scale: f64 = m.iter().map(|v| v * v).sum::<f64>().max(f64::MIN_POSITIVE);
        if off <= 1e-30 * scale {
            break;
        }
        for p in 0..n {
            for r in p + 1..n {
                let apr = m[p * n + r];
                if apr.abs() < 1e-300 {
                    continue;
                }
                let theta = (m[r * n + r] - m[p * n + p]) / (2.0 * apr);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (mkp, mkr) = (m[k * n + p], m[k * n + r]);
                    m[k * n + p] = c * mkp - s * mkr;
                    m[k * n + r] = s * mkp + c * mkr;
                }
                for k in 0..n {
                    let (mpk, mrk) = (m[p * n + k], m[r * n + k]);
                    m[p * n + k] = c * mpk - s * mrk;
                    m[r * n + k] = s * mpk + c * mrk;
                }
                for k in 0..n {
                    let (qkp, qkr) = (q[k * n + p], q[k * n + r]);
                    q[k * n + p] = c * qkp - s * qkr;
                    q[k * n + r] = s * qkp + c * qkr;
                }
            }
        }
    }
    ((0..n).map(|i| m[i * n + i]).collect(), q)
}

impl SensorTensors {
    /// Expand `A [N, M, T]` over an `H × W` frame (`H`, `W` multiples of the block).
    pub fn new(a: &MeasurementMatrix, height: usize, width: usize, device: &Device) -> tcsense_sensor::Result<Self> {
        a.plan(height, width)?; // checks the frame against the block
        let (bh, bw) = a.block();
        let av = a.a();
        let (n_sub, m, t) = av.dim();
        // per subpixel type: eigen-decomposition of A_n A_nᵀ
        let eig: Vec<(Vec<f64>, Vec<f64>)> = (0..n_sub)
            .map(|k| {
                let g: Vec<f64> = (0..m * m).map(|ij| (0..t).map(|j| av[(k, ij / m, j)] as f64 * av[(k, ij % m, j)] as f64).sum()).collect();
                jacobi_eigen(&g, m)
            })
            .collect();
        let hw = height * width;
        let sub = |p: usize| ((p / width) % bh) * bw + (p % width) % bw;
        let mut a_pix = vec![0f32; m * t * hw];
        let mut q_pix = vec![0f32; m * m * hw];
        let mut l_pix = vec![0f32; m * hw];
        for p in 0..hw {
            let k = sub(p);
            for mm in 0..m {
                for j in 0..t {
                    a_pix[(mm * t + j) * hw + p] = av[(k, mm, j)];
                }
                l_pix[mm * hw + p] = eig[k].0[mm].max(0.0) as f32;
                for i in 0..m {
                    q_pix[(mm * m + i) * hw + p] = eig[k].1[mm * m + i] as f32;
                }
            }
        }
        Ok(SensorTensors {
            a: Tensor::from_data(TensorData::new(a_pix, [1, m, t, height, width]), device),
            q: Tensor::from_data(TensorData::new(q_pix, [1, m, m, height, width]), device),
            lambda: Tensor::from_data(TensorData::new(l_pix, [1, m, height, width]), device),
            taps: m,
            bins: t,
            height,
            width,
        })
    }

    /// `A x`.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, _, h, w] = x.dims();
        // [1, M, T, H, W] * [B, 1, T, H, W] → sum over T
        (self.a.clone() * x.unsqueeze_dim::<5>(1)).sum_dim(2).reshape([b, self.taps, h, w])
    }

    /// `Aᵀ y`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn adjoint(&self, y: Tensor<4>) -> Tensor<4> {
        let [b, _, h, w] = y.dims();
        // [1, M, T, H, W] * [B, M, 1, H, W] → sum over M
        (self.a.clone() * y.unsqueeze_dim::<5>(2)).sum_dim(1).reshape([b, self.bins, h, w])
    }

    /// `Q diag(1/(λ + s)) Qᵀ v` per pixel; `s` is a scalar tensor `[1]`.
    ///
    /// # Shapes
    /// - `v`: `[B, M, H, W]` → `[B, M, H, W]`
    fn solve_aat(&self, v: Tensor<4>, s: Tensor<1>) -> Tensor<4> {
        let [b, m, h, w] = v.dims();
        // c_i = Σ_j Q[j][i] v_j: [1, Mj, Mi, H, W] * [B, Mj, 1, H, W] → sum over j
        let c = (self.q.clone() * v.unsqueeze_dim::<5>(2)).sum_dim(1).reshape([b, m, h, w]);
        let c = c / (self.lambda.clone() + s.reshape([1, 1, 1, 1]));
        // w_j = Σ_i Q[j][i] c_i: [1, Mj, Mi, H, W] * [B, 1, Mi, H, W] → sum over i
        (self.q.clone() * c.unsqueeze_dim::<5>(1)).sum_dim(2).reshape([b, m, h, w])
    }

    /// The normalised back-projection `Aᵀ(AAᵀ + εI)⁻¹ y`, `ε = 1e-3·λ_max`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn pinv(&self, y: Tensor<4>) -> Tensor<4> {
        let lmax: f32 = self.lambda.clone().max().into_scalar();
        let eps = Tensor::<1>::from_floats([1e-3 * lmax.max(1e-12)], &y.device());
        self.adjoint(self.solve_aat(y, eps))
    }

    /// Exact data consistency `(AᵀA + ρI)⁻¹ v` per pixel (Woodbury).
    ///
    /// # Shapes
    /// - `v`: `[B, T, H, W]`, `rho`: `[1]` → `[B, T, H, W]`
    pub fn data_consistency(&self, v: Tensor<4>, rho: Tensor<1>) -> Tensor<4> {
        let av = self.forward(v.clone());
        let w = self.solve_aat(av, rho.clone());
        (v - self.adjoint(w)) / rho.reshape([1, 1, 1, 1])
    }
}

impl AdmmNet {
    /// Reconstruct cubes from measurements.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn forward(&self, y: Tensor<4>, sensor: &SensorTensors) -> Tensor<4> {
        let aty = sensor.adjoint(y.clone());
        let mut z = sensor.pinv(y);
        let mut u = z.zeros_like();
        for st in &self.stages {
            let rho = st.log_rho.val().exp();
            let v = aty.clone() + (z.clone() - u.clone()) * rho.clone().reshape([1, 1, 1, 1]);
            let x = sensor.data_consistency(v, rho);
            let xu = x.clone() + u.clone();
            let h = relu(st.conv1.forward(xu.clone()));
            let h = relu(st.conv2.forward(h));
            z = xu + st.conv3.forward(h);
            u = u + (x - z.clone()) * st.eta.val().reshape([1, 1, 1, 1]);
        }
        z
    }

    /// Learned `ρ` per stage.
    pub fn rhos(&self) -> Vec<f32> {
        self.stages.iter().map(|s| s.log_rho.val().exp().into_scalar::<f32>()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::SensorParams;

    #[test]
    fn jacobi_diagonalises() {
        let a = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 1.0];
        let (l, q) = jacobi_eigen(&a, 3);
        for i in 0..3 {
            for r in 0..3 {
                let aq: f64 = (0..3).map(|c| a[r * 3 + c] * q[c * 3 + i]).sum();
                assert!((aq - l[i] * q[r * 3 + i]).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn data_consistency_equals_a_direct_solve() {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
        let spec = SensorParams { irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }, ..SensorParams::from_codes(&codes) }.validate().unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let device = Device::flex();
        let st = SensorTensors::new(&a, 2, 4, &device).unwrap();
        let (t, h, w) = (8, 2, 4);
        let vals: Vec<f32> = (0..t * h * w).map(|i| ((i * 37 % 23) as f32) / 10.0 - 1.0).collect();
        let v = Tensor::<4>::from_data(TensorData::new(vals.clone(), [1, t, h, w]), &device);
        let rho = 0.37f64;
        let x: Vec<f32> = st.data_consistency(v, Tensor::from_floats([rho as f32], &device)).into_data().try_into_vec::<f32>().unwrap();
        let av = a.a();
        for r in 0..h {
            for c in 0..w {
                let n = (r % 2) * 2 + c % 2;
                // (AᵀA + ρI) x = v, solved by Gaussian elimination in f64
                let mut mtx: Vec<f64> = (0..t * t).map(|ij| (0..4).map(|m| av[(n, m, ij / t)] as f64 * av[(n, m, ij % t)] as f64).sum::<f64>() + if ij / t == ij % t { rho } else { 0.0 }).collect();
                let mut rhs: Vec<f64> = (0..t).map(|j| vals[(j * h + r) * w + c] as f64).collect();
                for k in 0..t {
                    let piv = mtx[k * t + k];
                    for i in k + 1..t {
                        let f = mtx[i * t + k] / piv;
                        for j in k..t {
                            mtx[i * t + j] -= f * mtx[k * t + j];
                        }
                        rhs[i] -= f * rhs[k];
                    }
                }
                let mut sol = vec![0.0; t];
                for k in (0..t).rev() {
                    sol[k] = (rhs[k] - (k + 1..t).map(|j| mtx[k * t + j] * sol[j]).sum::<f64>()) / mtx[k * t + k];
                }
                for j in 0..t {
                    let got = x[(j * h + r) * w + c] as f64;
                    assert!((got - sol[j]).abs() < 1e-4 * (1.0 + sol[j].abs()), "pixel ({r},{c}) bin {j}: {got} vs {}", sol[j]);
                }
            }
        }
        // the normalised back-projection satisfies A x0 ≈ y for consistent measurements y = A x
        let xr = Tensor::<4>::from_data(TensorData::new(vals.iter().map(|v| v.abs()).collect::<Vec<f32>>(), [1, t, h, w]), &device);
        let y = st.forward(xr);
        let yv: Vec<f32> = y.clone().into_data().try_into_vec::<f32>().unwrap();
        let back: Vec<f32> = st.forward(st.pinv(y)).into_data().try_into_vec::<f32>().unwrap();
        for (a, b) in back.iter().zip(&yv) {
            assert!((a - b).abs() < 1e-2 * (1.0 + b.abs()), "{a} vs {b}");
        }
    }
}
