//! The sensor as tensors (DESIGN §5, "layers under the decoders"): `A`, `Aᵀ`, the normalised
//! back-projection `Aᵀ(AAᵀ + εI)⁻¹` and the exact data-consistency solve `(AᵀA + ρI)⁻¹`
//! for one frame size, on any burn device.
//!
//! Pixel `(r, c)` of a frame has subpixel type `n = (r mod bh)·bw + (c mod bw)` and its own
//! `A_n [M, T]` (paper eq. 4). The Gram matrices `A_nA_nᵀ = Q_nΛ_nQ_nᵀ` come from
//! [`MeasurementMatrix::gram_eigen`], so `(ρI_M + A_nA_nᵀ)⁻¹ = Q_n diag(1/(ρ + λ_n)) Q_nᵀ`
//! and, by Woodbury, `(AᵀA + ρI)⁻¹ = (I − Aᵀ(ρI_M + AAᵀ)⁻¹A)/ρ` stay differentiable in `ρ`.
//!
//! ADMM's x-update `(AᵀA + ρI)⁻¹(Aᵀy + ρw)` is computed as `w + Aᵀ(ρI_M + AAᵀ)⁻¹(y − Aw)`
//! ([`SensorTensors::x_update`]; the same by the push-through identity). Forming the
//! right-hand side and dividing by `ρ` instead cancels terms of size `λ/ρ` times the result:
//! with the FLIm sensor's `λ ≈ 10⁴` (T = 256) and `ρ ≈ 0.1` that is 10⁵ times f32's rounding,
//! enough for two runtimes (or two thread counts) to disagree by a per cent.
//!
//! Two implementations of the same algebra: the fused frame-layout kernels of
//! `tcsense-kernels` ([`pixel_linear`], [`pixel_dc`]; what the networks run) and a reference
//! composed from burn ops in *block layout* (`[B, N, C, P]`, batched matmuls; differentiable
//! in `A` too), which the tests and `bench kernels` compare them with.

use burn::tensor::{Device, Tensor, TensorData};
use std::sync::Arc;
use tcsense_kernels::pixel::{pixel_dc, pixel_linear, woodbury_matrices, PixelMap, PixelSensor};
use tcsense_sensor::matrix::MATCHED_EPS;
use tcsense_sensor::waveform::subpixel;
use tcsense_sensor::MeasurementMatrix;

/// The sensor model as tensors for one frame size, in *block layout*: a frame `[B, C, H, W]`
/// is rearranged to `[B, N, C, P]` (subpixel type `n`, `P = (H/bh)·(W/bw)` blocks), where the
/// per-pixel operators become small batched matrix products: `A_n [M, T]`, `A_nᵀ` and
/// `(ρI + A_nA_nᵀ)⁻¹ = Q_n diag(1/(ρ + λ_n)) Q_nᵀ`.
#[derive(Debug, Clone)]
pub struct SensorTensors {
    /// `A` per subpixel type, `[1, N, M, T]`.
    pub a: Tensor<4>,
    /// `Aᵀ`, `[1, N, T, M]`.
    pub at: Tensor<4>,
    /// Eigenvectors of `A_nA_nᵀ`, `[1, N, M, M]` (columns).
    pub q: Tensor<4>,
    /// `Qᵀ`, `[1, N, M, M]`.
    pub qt: Tensor<4>,
    /// Eigenvalues, `[1, N, 1, M]`.
    pub lambda: Tensor<4>,
    /// The range fit's matched filters `F_n` at the bin centres, ambient projected out
    /// ([`MeasurementMatrix::matched_filters`]), `[1, N, T, M]`.
    pub matched: Tensor<4>,
    pub taps: usize,
    pub bins: usize,
    pub height: usize,
    pub width: usize,
    pub block: (usize, usize),
    /// The same operators for the fused frame-layout kernels of `tcsense_kernels::pixel`: `A`,
    /// `Aᵀ`, the back-projection `Aᵀ(AAᵀ + εI)⁻¹` and the data-consistency solve.
    pub fused: FusedSensor,
    /// Whether `a`/`at` carry a graph to learnable codes ([`Self::with_matrix`]): the operators
    /// then run in block layout from burn ops, differentiable in `A`.
    pub differentiable: bool,
    /// `λ_{n(r,c), j}` at every pixel, `[1, M, H, W]` (for the fused x-update).
    pub lambda_frame: Tensor<4>,
    /// Whether the device has no fused kernels (anything but the CPU `flex` device, e.g. the
    /// wgpu GPU backend): the operators then run in block layout from burn ops too.
    pub composed: bool,
    /// The matrix itself, for what runs off the tensors (the lifetime fit's evidence).
    pub matrix: MeasurementMatrix,
}

/// [`MeasurementMatrix::matched_filters`] from burn ops, differentiable in `A` (deep sensing):
/// `s = A1`, `P = I − ssᵀ/‖s‖²`, rows `(P a_t)ᵀ‖P a_t‖/(‖P a_t‖² + ε²‖a_t‖²)`.
///
/// # Shapes
/// - `a`: `[1, N, M, T]` → `[1, N, T, M]`
pub fn matched_filters(a: Tensor<4>) -> Tensor<4> {
    let s = a.clone().sum_dim(3); // [1, N, M, 1]
    let ss = s.clone().powi_scalar(2).sum_dim(2).clamp_min(1e-30); // [1, N, 1, 1]
    let along = s.clone().swap_dims(2, 3).matmul(a.clone()) / ss; // [1, N, 1, T]
    let p = a.clone() - s * along; // [1, N, M, T]
    let pp = p.clone().powi_scalar(2).sum_dim(2); // [1, N, 1, T]
    let aa = a.clone().powi_scalar(2).sum_dim(2) * (MATCHED_EPS * MATCHED_EPS) as f32;
    let scale = pp.clone().add_scalar(1e-30).sqrt() / (pp + aa).clamp_min(1e-30);
    (p * scale).swap_dims(2, 3)
}

/// The per-pixel operators of [`SensorTensors`] for [`pixel_linear`] and [`pixel_dc`].
#[derive(Debug, Clone)]
pub struct FusedSensor {
    pub a: Arc<PixelMap>,
    pub at: Arc<PixelMap>,
    pub pinv: Arc<PixelMap>,
    pub dc: Arc<PixelSensor>,
    /// `Q_nᵀ`, `M → M`.
    pub qt: Arc<PixelMap>,
    /// `A_nᵀQ_n` (formed in f64), `M → T`.
    pub atq: Arc<PixelMap>,
    /// The matched filters `F_n` ([`MeasurementMatrix::matched_filters`]), `M → T`.
    pub matched: Arc<PixelMap>,
}

impl SensorTensors {
    /// Prepare `A [N, M, T]` for `H × W` frames (`H`, `W` multiples of the block).
    pub fn new(a: &MeasurementMatrix, height: usize, width: usize, device: &Device) -> tcsense_sensor::Result<Self> {
        a.plan(height, width)?; // checks the frame against the block
        let av = a.a();
        let (n_sub, m, t) = av.dim();
        let (lambda, q) = a.gram_eigen(); // [N, M], [N, M, M]
        let mut a_v = vec![0f32; n_sub * m * t];
        let mut at_v = vec![0f32; n_sub * t * m];
        let mut q_v = vec![0f32; n_sub * m * m];
        let mut qt_v = vec![0f32; n_sub * m * m];
        let mut l_v = vec![0f32; n_sub * m];
        for k in 0..n_sub {
            for mm in 0..m {
                for j in 0..t {
                    a_v[(k * m + mm) * t + j] = av[(k, mm, j)];
                    at_v[(k * t + j) * m + mm] = av[(k, mm, j)];
                }
            }
            for r in 0..m {
                l_v[k * m + r] = lambda[(k, r)].max(0.0) as f32;
                for c in 0..m {
                    q_v[(k * m + r) * m + c] = q[(k, r, c)] as f32;
                    qt_v[(k * m + c) * m + r] = q[(k, r, c)] as f32;
                }
            }
        }
        // Aᵀ(AAᵀ + εI)⁻¹ = Aᵀ Q diag(1/(λ + ε)) Qᵀ, ε = 1e-3·λ_max
        let lmax = l_v.iter().fold(0f32, |a, &b| a.max(b)).max(1e-12);
        let k_eps = woodbury_matrices(&q_v, &l_v, m, 1e-3 * lmax); // [N, M, M]
        let mut pinv_v = vec![0f32; n_sub * t * m];
        for k in 0..n_sub {
            for j in 0..t {
                for c in 0..m {
                    pinv_v[(k * t + j) * m + c] = (0..m).map(|r| at_v[(k * t + j) * m + r] * k_eps[(k * m + r) * m + c]).sum();
                }
            }
        }
        // A_nᵀQ_n in f64: a column with λ ≈ 0 is ≈ 0 and must stay so
        let mut atq_v = vec![0f32; n_sub * t * m];
        for k in 0..n_sub {
            for j in 0..t {
                for c in 0..m {
                    atq_v[(k * t + j) * m + c] = (0..m).map(|r| av[(k, r, j)] as f64 * q[(k, r, c)]).sum::<f64>() as f32;
                }
            }
        }
        let matched_v: Vec<f32> = a.matched_filters().iter().map(|&v| v as f32).collect(); // [N, T, M]
        let block = a.block();
        let (bh, bw) = block;
        let mut lf = vec![0f32; m * height * width];
        for j in 0..m {
            for r in 0..height {
                for c in 0..width {
                    lf[(j * height + r) * width + c] = l_v[subpixel(r, c, (bh, bw)) * m + j];
                }
            }
        }
        let fused = FusedSensor {
            a: Arc::new(PixelMap::new(block, m, t, width, &a_v)),
            at: Arc::new(PixelMap::new(block, t, m, width, &at_v)),
            pinv: Arc::new(PixelMap::new(block, t, m, width, &pinv_v)),
            dc: Arc::new(PixelSensor::new(block, m, t, width, &a_v, &q_v, &l_v)),
            qt: Arc::new(PixelMap::new(block, m, m, width, &qt_v)),
            atq: Arc::new(PixelMap::new(block, t, m, width, &atq_v)),
            matched: Arc::new(PixelMap::new(block, t, m, width, &matched_v)),
        };
        Ok(SensorTensors {
            fused,
            a: Tensor::from_data(TensorData::new(a_v, [1, n_sub, m, t]), device),
            at: Tensor::from_data(TensorData::new(at_v, [1, n_sub, t, m]), device),
            q: Tensor::from_data(TensorData::new(q_v, [1, n_sub, m, m]), device),
            qt: Tensor::from_data(TensorData::new(qt_v, [1, n_sub, m, m]), device),
            lambda: Tensor::from_data(TensorData::new(l_v, [1, n_sub, 1, m]), device),
            matched: Tensor::from_data(TensorData::new(matched_v, [1, n_sub, t, m]), device),
            lambda_frame: Tensor::from_data(TensorData::new(lf, [1, m, height, width]), device),
            taps: m,
            bins: t,
            height,
            width,
            block: a.block(),
            differentiable: false,
            composed: !tcsense_kernels::runs_kernels(device),
            matrix: a.clone(),
        })
    }

    /// Frame to block layout.
    ///
    /// # Shapes
    /// - `x`: `[B, C, H, W]` → `[B, N, C, P]`
    pub fn to_blocks(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, c, h, w] = x.dims();
        let (bh, bw) = self.block;
        let (hb, wb) = (h / bh, w / bw);
        x.reshape([b, c, hb, bh, wb, bw]) // [B, C, H', bh, W', bw]
            .permute([0, 3, 5, 1, 2, 4]) // [B, bh, bw, C, H', W']
            .reshape([b, bh * bw, c, hb * wb])
    }

    /// Block layout back to frames.
    ///
    /// # Shapes
    /// - `z`: `[B, N, C, P]` → `[B, C, H, W]`
    pub fn from_blocks(&self, z: Tensor<4>) -> Tensor<4> {
        let [b, _, c, _] = z.dims();
        let (bh, bw) = self.block;
        let (hb, wb) = (self.height / bh, self.width / bw);
        z.reshape([b, bh, bw, c, hb, wb]) // [B, bh, bw, C, H', W']
            .permute([0, 3, 4, 1, 5, 2]) // [B, C, H', bh, W', bw]
            .reshape([b, c, self.height, self.width])
    }

    /// `A x` in block layout: `[B, N, T, P]` → `[B, N, M, P]`.
    fn a_blocks(&self, x: Tensor<4>) -> Tensor<4> {
        self.a.clone().matmul(x)
    }

    /// `Aᵀ y` in block layout: `[B, N, M, P]` → `[B, N, T, P]`.
    fn at_blocks(&self, y: Tensor<4>) -> Tensor<4> {
        self.at.clone().matmul(y)
    }

    /// `(sI + AAᵀ)⁻¹ v` in block layout: `[B, N, M, P]` → `[B, N, M, P]`; `s` is `[1]`.
    ///
    /// With a differentiable `A`, one Newton step `X = X₀(2I − (sI + AAᵀ)X₀)` around the exact
    /// inverse `X₀` (the eigendecomposition, a constant) keeps the value (`(sI + AAᵀ)X₀ = I`)
    /// and gives the exact derivative `dX = −X₀ d(AAᵀ) X₀`.
    fn solve_aat(&self, v: Tensor<4>, s: Tensor<1>) -> Tensor<4> {
        let s4 = s.reshape([1, 1, 1, 1]);
        let inv = (self.lambda.clone() + s4.clone()).recip(); // [1, N, 1, M]
        let k = (self.q.clone() * inv).matmul(self.qt.clone()); // [1, N, M, M]
        let x0 = k.clone().matmul(v);
        if !self.differentiable {
            return x0;
        }
        let m_x0 = x0.clone() * s4 + self.a_blocks(self.at_blocks(x0.clone()));
        x0.mul_scalar(2.0) - k.matmul(m_x0)
    }

    /// The same sensor with `A [N, M, T]` taken from `a` (e.g. learnable codes' `A(θ)`, equal
    /// in value to the matrix this was built from): every operator then follows `a`'s graph.
    pub fn with_matrix(mut self, a: Tensor<3>) -> Self {
        let a: Tensor<4> = a.unsqueeze_dim(0);
        self.at = a.clone().swap_dims(2, 3);
        self.matched = matched_filters(a.clone());
        self.a = a;
        self.differentiable = true;
        self
    }

    /// Whether the operators run in block layout from burn ops (differentiable in `A`, or on a
    /// device without the fused kernels) rather than through the fused kernels.
    fn in_blocks(&self) -> bool {
        self.differentiable || self.composed
    }

    /// `A x`.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        if self.in_blocks() {
            return self.from_blocks(self.a_blocks(self.to_blocks(x)));
        }
        pixel_linear(x, self.fused.a.clone())
    }

    /// `Aᵀ y`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn adjoint(&self, y: Tensor<4>) -> Tensor<4> {
        if self.in_blocks() {
            return self.from_blocks(self.at_blocks(self.to_blocks(y)));
        }
        pixel_linear(y, self.fused.at.clone())
    }

    /// The matched filters `F y` ([`Self::matched`]): each pixel's correlation with a return at
    /// every bin centre, ambient light projected out.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn matched(&self, y: Tensor<4>) -> Tensor<4> {
        if self.in_blocks() {
            return self.from_blocks(self.matched.clone().matmul(self.to_blocks(y)));
        }
        pixel_linear(y, self.fused.matched.clone())
    }

    /// The normalised back-projection `Aᵀ(AAᵀ + εI)⁻¹ y`, `ε = 1e-3·λ_max`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn pinv(&self, y: Tensor<4>) -> Tensor<4> {
        if self.in_blocks() {
            return self.pinv_blocks(y);
        }
        pixel_linear(y, self.fused.pinv.clone())
    }

    /// [`Self::pinv`] composed from burn ops in block layout (the reference for the fused one).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn pinv_blocks(&self, y: Tensor<4>) -> Tensor<4> {
        let lmax: f32 = self.lambda.clone().max().into_scalar();
        let eps = Tensor::<1>::from_floats([1e-3 * lmax.max(1e-12)], &y.device());
        self.from_blocks(self.at_blocks(self.solve_aat(self.to_blocks(y), eps)))
    }

    /// Exact data consistency `(AᵀA + ρI)⁻¹ v` per pixel (Woodbury), in block layout, composed
    /// from burn ops: differentiable in `A` as well (for learning the codes), and the
    /// reference for the fused [`Self::data_consistency`].
    ///
    /// # Shapes
    /// - `v`: `[B, N, T, P]`, `rho`: `[1]` → `[B, N, T, P]`
    pub fn data_consistency_blocks(&self, v: Tensor<4>, rho: Tensor<1>) -> Tensor<4> {
        let w = self.solve_aat(self.a_blocks(v.clone()), rho.clone());
        (v - self.at_blocks(w)) / rho.reshape([1, 1, 1, 1])
    }

    /// ADMM's x-update `x = (AᵀA + ρI)⁻¹(Aᵀy + ρw)`, computed as `w + Aᵀ(ρI + AAᵀ)⁻¹(y − Aw)`
    /// (see the module documentation: no division by `ρ`, so rounding is not amplified by
    /// `λ/ρ`); differentiable in `w`, `y` and `ρ` (and in `A` with [`Self::with_matrix`]).
    ///
    /// # Shapes
    /// - `w`: `[B, T, H, W]`, `y`: `[B, M, H, W]`, `rho`: `[1]` → `[B, T, H, W]`
    pub fn x_update(&self, w: Tensor<4>, y: Tensor<4>, rho: Tensor<1>) -> Tensor<4> {
        if self.in_blocks() {
            let wb = self.to_blocks(w);
            let r = self.to_blocks(y) - self.a_blocks(wb.clone());
            return self.from_blocks(wb + self.at_blocks(self.solve_aat(r, rho)));
        }
        // Q_nᵀ r, scaled by 1/(ρ + λ) per eigenvector, back through A_nᵀQ_n
        let r = y - pixel_linear(w.clone(), self.fused.a.clone());
        let coef = (self.lambda_frame.clone() + rho.reshape([1, 1, 1, 1])).recip();
        w + pixel_linear(pixel_linear(r, self.fused.qt.clone()) * coef, self.fused.atq.clone())
    }

    /// Exact data consistency on frames, fused ([`pixel_dc`]): differentiable in `v` and `ρ`.
    ///
    /// # Shapes
    /// - `v`: `[B, T, H, W]`, `rho`: `[1]` → `[B, T, H, W]`
    pub fn data_consistency(&self, v: Tensor<4>, rho: Tensor<1>) -> Tensor<4> {
        if self.in_blocks() {
            return self.from_blocks(self.data_consistency_blocks(self.to_blocks(v), rho));
        }
        pixel_dc(v, rho, self.fused.dc.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;
    use tcsense_sensor::SensorParams;

    /// `x` with `M x = b` for a dense `n × n` system (row-major), by Gaussian elimination in f64
    /// (the reference the solves are checked against; the systems here are well conditioned).
    fn solve_f64(mut mtx: Vec<f64>, mut rhs: Vec<f64>) -> Vec<f64> {
        let n = rhs.len();
        for k in 0..n {
            for i in k + 1..n {
                let f = mtx[i * n + k] / mtx[k * n + k];
                for j in k..n {
                    mtx[i * n + j] -= f * mtx[k * n + j];
                }
                rhs[i] -= f * rhs[k];
            }
        }
        let mut sol = vec![0.0; n];
        for k in (0..n).rev() {
            sol[k] = (rhs[k] - (k + 1..n).map(|j| mtx[k * n + j] * sol[j]).sum::<f64>()) / mtx[k * n + k];
        }
        sol
    }

    /// With `A` as a graph tensor the operators keep their values, and the gradient of the
    /// data-consistency solve in `A` matches central differences (the inverse's derivative
    /// comes from one Newton step around the constant eigendecomposition).
    #[test]
    fn differentiable_operators_keep_values_and_differentiate_in_a() {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
        let spec = SensorParams {
            irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            ..SensorParams::from_codes(&codes)
        }
        .validate()
        .unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let device = Device::flex().autodiff();
        let st = SensorTensors::new(&a, 2, 4, &device).unwrap();
        let av: Vec<f32> = a.a().iter().copied().collect();
        let a_tensor = |vals: Vec<f32>| Tensor::<3>::from_data(TensorData::new(vals, [4, 4, 8]), &device);
        let v = Tensor::<4>::from_data(
            TensorData::new((0..64).map(|i| ((i * 37 % 23) as f32) / 10.0 - 1.0).collect::<Vec<f32>>(), [1, 8, 2, 4]),
            &device,
        );
        let y = Tensor::<4>::from_data(
            TensorData::new((0..32).map(|i| ((i * 13 % 17) as f32) / 5.0).collect::<Vec<f32>>(), [1, 4, 2, 4]),
            &device,
        );
        let rho = || Tensor::<1>::from_floats([0.37f32], &device);
        let vec = |t: Tensor<4>| t.into_data().try_into_vec::<f32>().unwrap();
        let close = |p: Vec<f32>, q: Vec<f32>, what: &str| {
            let peak = p.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
            for (u, w) in p.iter().zip(&q) {
                assert!((u - w).abs() <= 1e-4 * peak, "{what}: {u} vs {w}");
            }
        };
        let diff = st.clone().with_matrix(a_tensor(av.clone()));
        close(vec(diff.forward(v.clone())), vec(st.forward(v.clone())), "A x");
        close(vec(diff.adjoint(y.clone())), vec(st.adjoint(y.clone())), "Aᵀ y");
        close(vec(diff.pinv(y.clone())), vec(st.pinv(y.clone())), "back-projection");
        close(vec(diff.matched(y.clone())), vec(st.matched(y.clone())), "matched filters");
        close(vec(diff.data_consistency(v.clone(), rho())), vec(st.data_consistency(v.clone(), rho())), "data consistency");
        // gradient in A against central differences
        let loss = |vals: Vec<f32>, grad: bool| {
            let a = a_tensor(vals);
            let a = if grad { a.require_grad() } else { a };
            let out = st.clone().with_matrix(a.clone()).data_consistency(v.clone(), rho()) * v.clone();
            (a, out.sum())
        };
        let (a_req, total) = loss(av.clone(), true);
        let grads = total.backward();
        let g = a_req.grad(&grads).expect("gradient").into_data().try_into_vec::<f32>().unwrap();
        for idx in [0usize, 9, 37, 70, 101, 127] {
            let eps = 1e-3f32;
            let (mut up, mut down) = (av.clone(), av.clone());
            up[idx] += eps;
            down[idx] -= eps;
            let f = |x: Vec<f32>| loss(x, false).1.into_scalar::<f32>() as f64;
            let fd = (f(up) - f(down)) / (2.0 * eps as f64);
            assert!((g[idx] as f64 - fd).abs() <= 2e-2 * fd.abs().max(0.1), "dA[{idx}]: autodiff {} vs finite differences {fd}", g[idx]);
        }
    }

    /// The x-update on the FLIm sensor (heterodyne K = 8, T = 256: `λ` up to ~10⁴) with a small
    /// `ρ`: within 1e-5 of the f64 solution, fused and composed, where the Woodbury form on the
    /// formed right-hand side loses 10⁻³ or more (the burn/ONNX Runtime disagreement of
    /// trained FLIm networks).
    #[test]
    fn x_update_is_accurate_where_the_woodbury_form_cancels() {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 32, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 5).unwrap();
        let spec = SensorParams {
            irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            sampling: tcsense_sensor::params::Sampling::Heterodyne(8),
            ..SensorParams::from_codes(&codes)
        }
        .validate()
        .unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let (m, t, h, w) = (4, 256, 2, 4);
        assert_eq!(a.bins(), t);
        let av = a.a();
        // a decay per pixel as w, and measurements of another one
        let wv: Vec<f32> = (0..t * h * w).map(|i| (-((i / (h * w)) as f32) / 20.0).exp() * (1.0 + (i % 7) as f32 / 10.0)).collect();
        let yv: Vec<f32> = (0..m * h * w).map(|i| 40.0 + (i * 13 % 11) as f32).collect();
        let rho = 0.05f64;
        // f64: x = w + Aᵀ(ρI + AAᵀ)⁻¹(y − Aw) per pixel, the M × M system by Gaussian elimination
        let mut want = vec![0f64; t * h * w];
        for r in 0..h {
            for c in 0..w {
                let n = (r % 2) * 2 + c % 2;
                let px = |j: usize| (j * h + r) * w + c;
                let res: Vec<f64> = (0..m)
                    .map(|k| yv[(k * h + r) * w + c] as f64 - (0..t).map(|j| av[(n, k, j)] as f64 * wv[px(j)] as f64).sum::<f64>())
                    .collect();
                let mtx: Vec<f64> = (0..m * m)
                    .map(|ij| {
                        (0..t).map(|j| av[(n, ij / m, j)] as f64 * av[(n, ij % m, j)] as f64).sum::<f64>()
                            + if ij / m == ij % m { rho } else { 0.0 }
                    })
                    .collect();
                let sol = solve_f64(mtx, res);
                for j in 0..t {
                    want[px(j)] = wv[px(j)] as f64 + (0..m).map(|k| av[(n, k, j)] as f64 * sol[k]).sum::<f64>();
                }
            }
        }
        let scale = want.iter().fold(0f64, |acc, v| acc.max(v.abs()));
        let err = |got: Tensor<4>| {
            let got: Vec<f32> = got.into_data().try_into_vec::<f32>().unwrap();
            got.iter().zip(&want).fold(0f64, |acc, (g, w)| acc.max((*g as f64 - w).abs())) / scale
        };
        let device = Device::flex();
        let st = SensorTensors::new(&a, h, w, &device).unwrap();
        let (wt, yt) = (
            Tensor::<4>::from_data(TensorData::new(wv.clone(), [1, t, h, w]), &device),
            Tensor::<4>::from_data(TensorData::new(yv.clone(), [1, m, h, w]), &device),
        );
        let rho_t = || Tensor::<1>::from_floats([rho as f32], &device);
        let fused = err(st.x_update(wt.clone(), yt.clone(), rho_t()));
        let composed = err(st.clone().with_matrix(st.a.clone().squeeze_dim(0)).x_update(wt.clone(), yt.clone(), rho_t()));
        let woodbury = err(st.data_consistency(st.adjoint(yt) + wt * rho as f32, rho_t()));
        assert!(fused < 1e-5 && composed < 1e-5, "x-update error of the scale: fused {fused:e}, composed {composed:e}");
        assert!(
            woodbury > 1e-3,
            "the Woodbury form on Aᵀy + ρw cancels ({woodbury:e}); if not, this test no longer shows why x_update exists"
        );
    }

    #[test]
    fn data_consistency_equals_a_direct_solve() {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
        let spec = SensorParams {
            irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            ..SensorParams::from_codes(&codes)
        }
        .validate()
        .unwrap();
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
                let mtx: Vec<f64> = (0..t * t)
                    .map(|ij| {
                        (0..4).map(|m| av[(n, m, ij / t)] as f64 * av[(n, m, ij % t)] as f64).sum::<f64>()
                            + if ij / t == ij % t { rho } else { 0.0 }
                    })
                    .collect();
                let sol = solve_f64(mtx, (0..t).map(|j| vals[(j * h + r) * w + c] as f64).collect());
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
