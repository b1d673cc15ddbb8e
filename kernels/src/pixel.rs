//! Fused per-pixel sensor operators in frame layout `[B, C, H, W]`, as burn backend extension
//! ops with handwritten backward passes.
//!
//! Pixel `(r, c)` has subpixel type `n = (r mod bh)·bw + (c mod bw)` and its own `A_n [M, T]`.
//!
//! - [`pixel_linear`]: `y(r, c) = P_n x(r, c)` for a per-subpixel matrix `P_n [O, I]`
//!   (`Aᵀ`, the normalised back-projection `Aᵀ(AAᵀ + εI)⁻¹`, …); its gradient is `P_nᵀ g`.
//! - [`pixel_dc`]: ADMM-Net's exact data-consistency step `x = (AᵀA + ρI)⁻¹ v` through
//!   Woodbury, `x = (v − A_nᵀ Q_n diag(1/(ρ + λ_n)) Q_nᵀ A_n v)/ρ`. The map is symmetric and
//!   linear in `v`, so `∂L/∂v = (AᵀA + ρI)⁻¹ g`, and `∂x/∂ρ = −(AᵀA + ρI)⁻¹ x` gives
//!   `∂L/∂ρ = −⟨(AᵀA + ρI)⁻¹ g, x⟩`.
//!
//! The composed version in `tcsense_models::SensorTensors` (block layout, batched matmuls) does
//! the same algebra with burn ops, moving every cube through two permutations per call; these
//! kernels read each voxel once and write it once. Coefficients are laid out per row class
//! `r mod bh` and column (`[bh][O][I][W]`), so the inner loops are plain multiply-adds over a
//! row of pixels, and rows are processed in parallel bands.
#![allow(unsafe_code)] // disjoint parallel writes into the output planes, see `par_bands`

use std::sync::Arc;

use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::{Flex, FlexTensor};
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch, TensorMetadata};
use burn::tensor::{Shape, Tensor, TensorData};
use rayon::prelude::*;

use crate::conv_op::with_f32;
use crate::plane::SharedOut;

/// A per-subpixel linear map `P_n [O, I]` laid out for a frame `W` pixels wide.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelMap {
    /// Block `(bh, bw)`.
    pub block: (usize, usize),
    /// Output channels `O`.
    pub outputs: usize,
    /// Input channels `I`.
    pub inputs: usize,
    /// Frame width `W`.
    pub width: usize,
    /// `coef[((ry·O + o)·I + i)·W + c] = P_{n(ry, c)}[o, i]`.
    coef: Vec<f32>,
}

impl PixelMap {
    /// Build from the per-subpixel matrices `p[n] = P_n` (row-major `[O, I]`, `n < bh·bw`).
    ///
    /// # Shapes
    /// - `p`: `[N, O, I]` → a map for frames `W` wide
    pub fn new(block: (usize, usize), outputs: usize, inputs: usize, width: usize, p: &[f32]) -> Self {
        let (bh, bw) = block;
        assert_eq!(p.len(), bh * bw * outputs * inputs, "PixelMap: P must be [N, O, I]");
        assert!(width % bw == 0, "PixelMap: width {width} is not a multiple of the block width {bw}");
        let mut coef = vec![0.0f32; bh * outputs * inputs * width];
        for ry in 0..bh {
            for o in 0..outputs {
                for i in 0..inputs {
                    for c in 0..width {
                        let n = ry * bw + c % bw;
                        coef[((ry * outputs + o) * inputs + i) * width + c] = p[(n * outputs + o) * inputs + i];
                    }
                }
            }
        }
        PixelMap { block, outputs, inputs, width, coef }
    }

    /// The map `P_nᵀ` (the adjoint, which is the gradient of `pixel_linear`).
    pub fn transposed(&self) -> Self {
        let (bh, (o_n, i_n, w)) = (self.block.0, (self.outputs, self.inputs, self.width));
        let mut coef = vec![0.0f32; self.coef.len()];
        for ry in 0..bh {
            for o in 0..o_n {
                for i in 0..i_n {
                    let src = ((ry * o_n + o) * i_n + i) * w;
                    let dst = ((ry * i_n + i) * o_n + o) * w;
                    coef[dst..dst + w].copy_from_slice(&self.coef[src..src + w]);
                }
            }
        }
        PixelMap { block: self.block, outputs: i_n, inputs: o_n, width: w, coef }
    }

    /// The coefficients of row class `ry`, output `o`, input `i`: one per column.
    fn row(&self, ry: usize, o: usize, i: usize) -> &[f32] {
        let s = ((ry * self.outputs + o) * self.inputs + i) * self.width;
        &self.coef[s..s + self.width]
    }

    /// `y = P x` on a `[B, I, H, W]` buffer.
    ///
    /// # Shapes
    /// - `x`: `[B, I, H, W]` → `y`: `[B, O, H, W]`
    pub fn apply(&self, x: &[f32], dims: [usize; 4], y: &mut [f32]) {
        let [b, i_n, h, w] = dims;
        assert!(
            i_n == self.inputs && w == self.width && h % self.block.0 == 0,
            "PixelMap::apply: {dims:?} for {}→{} over {} columns",
            self.inputs,
            self.outputs,
            self.width
        );
        assert_eq!(x.len(), b * i_n * h * w, "PixelMap::apply: x");
        let hw = h * w;
        par_bands(y, [b, self.outputs, h, w], |bi, y0, planes| {
            simd(|| {
                let xb = &x[bi * i_n * hw..(bi + 1) * i_n * hw];
                for (k, yr) in (y0..).zip(0..planes[0].len() / w) {
                    let ry = k % self.block.0;
                    for (o, plane) in planes.iter_mut().enumerate() {
                        let out = &mut plane[yr * w..(yr + 1) * w];
                        out.fill(0.0);
                        for i in 0..i_n {
                            let xi = &xb[(i * h + k) * w..(i * h + k + 1) * w];
                            for ((d, &p), &v) in out.iter_mut().zip(self.row(ry, o, i)).zip(xi) {
                                *d += p * v;
                            }
                        }
                    }
                }
            })
        });
    }
}

/// The sensor for [`pixel_dc`]: `A_n` and the eigen-decomposition `A_nA_nᵀ = Q_n Λ_n Q_nᵀ`.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelSensor {
    /// `A` as a map `T → M`.
    pub a: PixelMap,
    /// `Q_n [M, M]` per subpixel (columns are eigenvectors), `[N, M, M]`.
    q: Vec<f32>,
    /// `λ_n [M]` per subpixel, `[N, M]`.
    lambda: Vec<f32>,
}

impl PixelSensor {
    /// # Shapes
    /// - `a`: `[N, M, T]`, `q`: `[N, M, M]`, `lambda`: `[N, M]`
    pub fn new(block: (usize, usize), taps: usize, bins: usize, width: usize, a: &[f32], q: &[f32], lambda: &[f32]) -> Self {
        let n = block.0 * block.1;
        assert_eq!(q.len(), n * taps * taps, "PixelSensor: Q must be [N, M, M]");
        assert_eq!(lambda.len(), n * taps, "PixelSensor: λ must be [N, M]");
        PixelSensor { a: PixelMap::new(block, taps, bins, width, a), q: q.to_vec(), lambda: lambda.to_vec() }
    }

    /// `K_n = Q_n diag(1/(ρ + λ_n)) Q_nᵀ` for every subpixel, as a map `M → M`.
    fn woodbury(&self, rho: f32) -> PixelMap {
        let m = self.a.outputs;
        PixelMap::new(self.a.block, m, m, self.a.width, &woodbury_matrices(&self.q, &self.lambda, m, rho))
    }

    /// `x = (AᵀA + ρI)⁻¹ v` on a `[B, T, H, W]` buffer.
    ///
    /// # Shapes
    /// - `v`: `[B, T, H, W]` → `x`: `[B, T, H, W]`
    pub fn dc(&self, v: &[f32], dims: [usize; 4], rho: f32, x: &mut [f32]) {
        let [b, t, h, w] = dims;
        let (a, m, bh) = (&self.a, self.a.outputs, self.a.block.0);
        assert!(t == a.inputs && w == a.width && h % bh == 0, "PixelSensor::dc: {dims:?} for T = {}, W = {}", a.inputs, a.width);
        assert_eq!(v.len(), b * t * h * w, "PixelSensor::dc: v");
        assert!(rho > 0.0, "PixelSensor::dc: ρ = {rho} must be > 0");
        let k = self.woodbury(rho);
        let hw = h * w;
        let inv_rho = 1.0 / rho;
        par_bands(x, [b, t, h, w], |bi, y0, planes| {
            simd(|| {
                let vb = &v[bi * t * hw..(bi + 1) * t * hw];
                // per band: w1 = A v and w2 = K w1, M rows of W pixels each
                let mut w1 = vec![0.0f32; m * w];
                let mut w2 = vec![0.0f32; m * w];
                for (r, yr) in (y0..).zip(0..planes[0].len() / w) {
                    let ry = r % bh;
                    let vrow = |j: usize| &vb[(j * h + r) * w..(j * h + r + 1) * w];
                    w1.fill(0.0);
                    for (mm, acc) in w1.chunks_exact_mut(w).enumerate() {
                        for j in 0..t {
                            for ((d, &p), &val) in acc.iter_mut().zip(a.row(ry, mm, j)).zip(vrow(j)) {
                                *d += p * val;
                            }
                        }
                    }
                    w2.fill(0.0);
                    for (mm, acc) in w2.chunks_exact_mut(w).enumerate() {
                        for (mj, src) in w1.chunks_exact(w).enumerate() {
                            for ((d, &p), &val) in acc.iter_mut().zip(k.row(ry, mm, mj)).zip(src) {
                                *d += p * val;
                            }
                        }
                    }
                    for (j, plane) in planes.iter_mut().enumerate() {
                        let out = &mut plane[yr * w..(yr + 1) * w];
                        out.copy_from_slice(vrow(j));
                        for (mm, src) in w2.chunks_exact(w).enumerate() {
                            for ((d, &p), &val) in out.iter_mut().zip(a.row(ry, mm, j)).zip(src) {
                                *d -= p * val;
                            }
                        }
                        out.iter_mut().for_each(|d| *d *= inv_rho);
                    }
                }
            })
        });
    }
}

/// `K_n = Q_n diag(1/(s + λ_n)) Q_nᵀ = (sI + A_nA_nᵀ)⁻¹` for every subpixel `n`.
///
/// # Shapes
/// - `q`: `[N, M, M]` (columns are eigenvectors), `lambda`: `[N, M]` → `[N, M, M]`
pub fn woodbury_matrices(q: &[f32], lambda: &[f32], m: usize, s: f32) -> Vec<f32> {
    let n_sub = lambda.len() / m.max(1);
    let mut k = vec![0.0f32; n_sub * m * m];
    for n in 0..n_sub {
        for r in 0..m {
            for c in 0..m {
                k[(n * m + r) * m + c] = (0..m).map(|j| q[(n * m + r) * m + j] * q[(n * m + c) * m + j] / (s + lambda[n * m + j])).sum();
            }
        }
    }
    k
}

/// Run `f` compiled for the best vector extension this CPU has (AVX-512 or AVX2+FMA on x86-64,
/// chosen at run time), so its multiply-add loops vectorise beyond the baseline SSE2. Code
/// reached from `f` must be inlined into it (`#[inline(always)]`) to be compiled that way.
#[inline(always)]
pub fn simd<R>(f: impl FnOnce() -> R) -> R {
    pulp::Arch::new().dispatch(f)
}

/// Rows per parallel band: a few thousand pixels per task.
fn band_rows(h: usize, w: usize) -> usize {
    (4096 / w.max(1)).clamp(1, h.max(1))
}

/// Run `f(b, y0, planes)` in parallel for every item `b` and band of rows `y0..y1`, where
/// `planes[c]` is `out[b, c, y0..y1, :]` (contiguous, `(y1 − y0)·W` elements).
///
/// The bands partition the rows and each `(b, band)` is visited once, so the mutable views
/// handed to different tasks never overlap.
fn par_bands<F>(out: &mut [f32], [b, c, h, w]: [usize; 4], f: F)
where
    F: Fn(usize, usize, &mut [&mut [f32]]) + Sync,
{
    assert_eq!(out.len(), b * c * h * w, "par_bands: output");
    if out.is_empty() {
        return;
    }
    let rows = band_rows(h, w);
    let bands = h.div_ceil(rows);
    let base = SharedOut { ptr: out.as_mut_ptr(), len: out.len() };
    (0..b * bands).into_par_iter().for_each(|task| {
        let (bi, j) = (task / bands, task % bands);
        let (y0, y1) = (j * rows, ((j + 1) * rows).min(h));
        let mut planes: Vec<&mut [f32]> = (0..c)
            .map(|ch| {
                let off = ((bi * c + ch) * h + y0) * w;
                // SAFETY: `off + (y1 − y0)·w ≤ out.len()`, and `(bi, ch, y0..y1)` ranges are
                // disjoint between tasks (see the function's doc); `out` stays borrowed
                // mutably for the whole loop.
                unsafe { std::slice::from_raw_parts_mut(base.base().add(off), (y1 - y0) * w) }
            })
            .collect();
        f(bi, y0, &mut planes);
    });
}

// ---- burn ops ---------------------------------------------------------------------------

/// `y(r, c) = P_{n(r,c)} x(r, c)`; differentiable in `x`.
///
/// # Shapes
/// - `x`: `[B, I, H, W]` → `[B, O, H, W]`
pub fn pixel_linear(x: Tensor<4>, map: Arc<PixelMap>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as PixelBackend>::pixel_linear(x.into_dispatch(), map))
}

/// `x = (AᵀA + ρI)⁻¹ v` per pixel; differentiable in `v` and `ρ`.
///
/// # Shapes
/// - `v`: `[B, T, H, W]`, `rho`: `[1]` → `[B, T, H, W]`
pub fn pixel_dc(v: Tensor<4>, rho: Tensor<1>, sensor: Arc<PixelSensor>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as PixelBackend>::pixel_dc(v.into_dispatch(), rho.into_dispatch(), sensor))
}

/// The backend extension behind [`pixel_linear`] and [`pixel_dc`].
#[backend_extension(Flex, Autodiff)]
pub trait PixelBackend: Backend {
    /// `[B, I, H, W]` → `[B, O, H, W]`
    fn pixel_linear(x: FloatTensor<Self>, map: Arc<PixelMap>) -> FloatTensor<Self>;
    /// `[B, T, H, W]`, `[1]` → `[B, T, H, W]`
    fn pixel_dc(v: FloatTensor<Self>, rho: FloatTensor<Self>, sensor: Arc<PixelSensor>) -> FloatTensor<Self>;
}

fn scalar(t: FlexTensor) -> f32 {
    let data = t.into_data().convert::<f32>();
    let v = data.try_into_vec::<f32>().expect("converted to f32");
    assert_eq!(v.len(), 1, "pixel_dc: ρ must have one element");
    v[0]
}

impl PixelBackend for Flex {
    fn pixel_linear(x: FlexTensor, map: Arc<PixelMap>) -> FlexTensor {
        with_f32(x, |x, [b, _, h, w]| {
            let mut y = vec![0.0f32; b * map.outputs * h * w];
            map.apply(x, [b, map.inputs, h, w], &mut y);
            FlexTensor::from_data(TensorData::new(y, Shape::from([b, map.outputs, h, w])))
        })
    }

    fn pixel_dc(v: FlexTensor, rho: FlexTensor, sensor: Arc<PixelSensor>) -> FlexTensor {
        let rho = scalar(rho);
        with_f32(v, |v, dims| {
            let mut x = vec![0.0f32; v.len()];
            sensor.dc(v, dims, rho, &mut x);
            FlexTensor::from_data(TensorData::new(x, Shape::from(dims)))
        })
    }
}

#[derive(Debug)]
struct PixelLinearStep;

impl<B: Backend + PixelBackend> Backward<B, 1> for PixelLinearStep {
    /// `P_nᵀ`
    type State = Arc<PixelMap>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        if let Some(node) = node {
            grads.register::<B>(node.id, B::pixel_linear(grad, ops.state));
        }
    }
}

#[derive(Debug)]
struct PixelDcStep;

impl<B: Backend + PixelBackend> Backward<B, 2> for PixelDcStep {
    /// `(x, ρ, sensor)`
    type State = (FloatTensor<B>, FloatTensor<B>, Arc<PixelSensor>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_v, node_rho] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, rho, sensor) = ops.state;
        let shape = rho.shape();
        let dv = B::pixel_dc(grad, rho, sensor); // (AᵀA + ρI)⁻¹ g
        if let Some(node) = node_rho {
            let drho = B::float_neg(B::float_sum(B::float_mul(dv.clone(), x)));
            grads.register::<B>(node.id, B::float_reshape(drho, shape));
        }
        if let Some(node) = node_v {
            grads.register::<B>(node.id, dv);
        }
    }
}

impl<B: Backend + PixelBackend, C: CheckpointStrategy> PixelBackend for Autodiff<B, C> {
    fn pixel_linear(x: FloatTensor<Self>, map: Arc<PixelMap>) -> FloatTensor<Self> {
        match PixelLinearStep.prepare::<C>([x.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let adjoint = Arc::new(map.transposed());
                prep.finish(adjoint, B::pixel_linear(x.into_primitive(), map))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::pixel_linear(x.into_primitive(), map)),
        }
    }

    fn pixel_dc(v: FloatTensor<Self>, rho: FloatTensor<Self>, sensor: Arc<PixelSensor>) -> FloatTensor<Self> {
        match PixelDcStep.prepare::<C>([v.node(), rho.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let rho_p = Self::inner(rho);
                let x = B::pixel_dc(v.into_primitive(), rho_p.clone(), sensor.clone());
                prep.finish((x.clone(), rho_p, sensor), x)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::pixel_dc(v.into_primitive(), Self::inner(rho), sensor)),
        }
    }
}
