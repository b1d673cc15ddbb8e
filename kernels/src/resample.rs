//! The U-Net's resampling as burn backend extension ops with handwritten backward passes:
//!
//! - [`max_pool2`]: 2×2 max-pooling with stride 2, `y[b, c, i, j] = max x[b, c, 2i + di, 2j + dj]`;
//!   its gradient goes to the first maximum of each window (row-major), as burn's does;
//! - [`upsample2`]: nearest-neighbour up-sampling by 2, `y[b, c, i, j] = x[b, c, ⌊i/2⌋, ⌊j/2⌋]`;
//!   its gradient is the 2×2 sum of the output gradient.
//!
//! burn-flex runs these through generic paths (a pooling kernel with indices; a reshape and
//! two `repeat_dim`s) that took about a quarter of a U-Net forward pass at 188×212; here each
//! is one pass over the output, in parallel over the `B·C` planes, with no `unsafe`.

use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::{Flex, FlexTensor};
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch};
use burn::tensor::{Shape, Tensor, TensorData};
use rayon::prelude::*;

use crate::conv_op::with_f32;

/// 2×2 max-pooling, stride 2; `H` and `W` must be even.
///
/// # Shapes
/// - `x`: `[B, C, H, W]` → `[B, C, H/2, W/2]`
pub fn max_pool2(x: Tensor<4>) -> Tensor<4> {
    if !crate::runs_kernels(&x.device()) {
        return burn::tensor::module::max_pool2d(x, burn::tensor::ops::MaxPoolOptions::new([2, 2]));
    }
    Tensor::from_dispatch(<Dispatch as ResampleBackend>::max_pool2(x.into_dispatch()))
}

/// Nearest-neighbour up-sampling by 2.
///
/// # Shapes
/// - `x`: `[B, C, H, W]` → `[B, C, 2H, 2W]`
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    if !crate::runs_kernels(&x.device()) {
        let [b, c, h, w] = x.dims();
        return x.reshape([b, c, h, 1, w, 1]).repeat_dim(3, 2).repeat_dim(5, 2).reshape([b, c, 2 * h, 2 * w]);
    }
    Tensor::from_dispatch(<Dispatch as ResampleBackend>::upsample2(x.into_dispatch()))
}

/// The backend extension behind [`max_pool2`] and [`upsample2`].
#[backend_extension(Flex, Autodiff)]
pub trait ResampleBackend: Backend {
    /// `[B, C, H, W]` → `[B, C, H/2, W/2]`
    fn max_pool2(x: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Input `[B, C, H, W]`, output gradient `[B, C, H/2, W/2]` → input gradient `[B, C, H, W]`
    fn max_pool2_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self>;
    /// `[B, C, H, W]` → `[B, C, 2H, 2W]`
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Output gradient `[B, C, 2H, 2W]` → input gradient `[B, C, H, W]` (2×2 sums)
    fn upsample2_backward(grad: FloatTensor<Self>) -> FloatTensor<Self>;
}

fn tensor(v: Vec<f32>, dims: [usize; 4]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(v, Shape::from(dims)))
}

/// Index in a `w`-wide plane of the first maximum of the 2×2 window at output `(i, j)`.
#[inline]
fn argmax2(plane: &[f32], w: usize, i: usize, j: usize) -> usize {
    let k = 2 * i * w + 2 * j;
    let mut best = k;
    for cand in [k + 1, k + w, k + w + 1] {
        if plane[cand] > plane[best] {
            best = cand;
        }
    }
    best
}

impl ResampleBackend for Flex {
    fn max_pool2(x: FlexTensor) -> FlexTensor {
        with_f32(x, |x, [b, c, h, w]| {
            assert!(h % 2 == 0 && w % 2 == 0, "max_pool2: {h}x{w} is not even");
            let (ho, wo) = (h / 2, w / 2);
            let mut y = vec![0f32; b * c * ho * wo];
            if !y.is_empty() {
                y.par_chunks_mut(ho * wo).zip(x.par_chunks(h * w)).for_each(|(out, plane)| {
                    for i in 0..ho {
                        for j in 0..wo {
                            out[i * wo + j] = plane[argmax2(plane, w, i, j)];
                        }
                    }
                });
            }
            tensor(y, [b, c, ho, wo])
        })
    }

    fn max_pool2_backward(x: FlexTensor, grad: FlexTensor) -> FlexTensor {
        with_f32(x, |x, [b, c, h, w]| {
            with_f32(grad, |g, _| {
                let (ho, wo) = (h / 2, w / 2);
                let mut dx = vec![0f32; b * c * h * w];
                if !dx.is_empty() {
                    dx.par_chunks_mut(h * w).zip(x.par_chunks(h * w)).zip(g.par_chunks(ho * wo)).for_each(|((out, plane), gp)| {
                        for i in 0..ho {
                            for j in 0..wo {
                                out[argmax2(plane, w, i, j)] = gp[i * wo + j];
                            }
                        }
                    });
                }
                tensor(dx, [b, c, h, w])
            })
        })
    }

    fn upsample2(x: FlexTensor) -> FlexTensor {
        with_f32(x, |x, [b, c, h, w]| {
            let (ho, wo) = (2 * h, 2 * w);
            let mut y = vec![0f32; b * c * ho * wo];
            if !y.is_empty() {
                y.par_chunks_mut(ho * wo).zip(x.par_chunks(h * w)).for_each(|(out, plane)| {
                    for (r, row) in out.chunks_mut(wo).enumerate() {
                        let src = &plane[(r / 2) * w..(r / 2 + 1) * w];
                        for (pair, &v) in row.chunks_mut(2).zip(src) {
                            pair.fill(v);
                        }
                    }
                });
            }
            tensor(y, [b, c, ho, wo])
        })
    }

    fn upsample2_backward(grad: FlexTensor) -> FlexTensor {
        with_f32(grad, |g, [b, c, h2, w2]| {
            let (h, w) = (h2 / 2, w2 / 2);
            let mut dx = vec![0f32; b * c * h * w];
            if !dx.is_empty() {
                dx.par_chunks_mut(h * w).zip(g.par_chunks(h2 * w2)).for_each(|(out, gp)| {
                    for i in 0..h {
                        for j in 0..w {
                            let k = 2 * i * w2 + 2 * j;
                            out[i * w + j] = gp[k] + gp[k + 1] + gp[k + w2] + gp[k + w2 + 1];
                        }
                    }
                });
            }
            tensor(dx, [b, c, h, w])
        })
    }
}

#[derive(Debug)]
struct MaxPoolStep;

impl<B: Backend + ResampleBackend> Backward<B, 1> for MaxPoolStep {
    /// The input, to find each window's maximum again.
    type State = FloatTensor<B>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        if let Some(node) = node {
            grads.register::<B>(node.id, B::max_pool2_backward(ops.state, grad));
        }
    }
}

#[derive(Debug)]
struct UpsampleStep;

impl<B: Backend + ResampleBackend> Backward<B, 1> for UpsampleStep {
    type State = ();

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        if let Some(node) = node {
            grads.register::<B>(node.id, B::upsample2_backward(grad));
        }
    }
}

impl<B: Backend + ResampleBackend, C: CheckpointStrategy> ResampleBackend for Autodiff<B, C> {
    fn max_pool2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        match MaxPoolStep.prepare::<C>([x.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let input = x.primitive().clone();
                prep.finish(input, B::max_pool2(x.into_primitive()))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::max_pool2(x.into_primitive())),
        }
    }

    fn max_pool2_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::from_inner(B::max_pool2_backward(Self::inner(x), Self::inner(grad)))
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        UpsampleStep.prepare::<C>([x.node()]).compute_bound().stateless(B::upsample2(x.into_primitive()))
    }

    fn upsample2_backward(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::from_inner(B::upsample2_backward(Self::inner(grad)))
    }
}
