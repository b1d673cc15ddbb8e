//! [`delay_conv3x3`]: one layer of ADMM-Net's delay-equivariant prior as a burn backend
//! extension — a 3×3 convolution over the frame of the bins `t − d`, `t`, `t + d` (circular in
//! `t`) stacked as channels — running the kernels of [`crate::delay`] on the CPU, forward and
//! both gradients, without building the stacked tensor.
//!
//! ```text
//! x [B, T, C_in, H, W] ──(kernels: gathered im2col)──────────────────▶ [B, T, C_out, H, W]
//!                      └─(composed: roll + cat → [B·T, 3·C_in, H, W] → conv2d)─┘
//! ```
//!
//! On another device than `Flex` or `Autodiff<Flex>` (the GPU build) it is the composed form, [`delay_conv3x3_composed`], which the kernels are tested against.

use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::{Flex, FlexTensor};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch};
use burn::tensor::{DType, FloatDType, Shape, Tensor, TensorData};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use crate::conv_op::{conv3x3, dims4, f32_contiguous, f32_slice, Conv3x3Backend};
use crate::delay::DelayConv3x3;

/// The bins `t − d`, `t`, `t + d` of every bin, circularly, stacked as channels: channel
/// `j·C + c` of bin `t` is channel `c` of bin `(t + (j − 1)·d) mod T` (a copy of three times
/// the input; [`delay_conv3x3`] reads the same values in place).
///
/// # Shapes
/// - `h`: `[B, T, C, H, W]` → `[B, T, 3C, H, W]`
pub fn delay_taps(h: Tensor<5>, d: usize) -> Tensor<5> {
    let t = h.dims()[1] as i64;
    let d = d as i64 % t;
    // roll_dim(s): out[t] = in[t − s]
    Tensor::cat(vec![h.clone().roll_dim(d, 1), h.clone(), h.roll_dim(-d, 1)], 2)
}

/// The delay-tap convolution: `y[b, t] = conv3x3(delay_taps(x, d)[b, t], weight) + bias`.
///
/// # Shapes
/// - `x`: `[B, T, C_in, H, W]`, `weight`: `[C_out, 3·C_in, 3, 3]`, `bias`: `[C_out]` →
///   `[B, T, C_out, H, W]`
pub fn delay_conv3x3(x: Tensor<5>, weight: Tensor<4>, bias: Tensor<1>, dilation: usize) -> Tensor<5> {
    if !crate::runs_kernels(&x.device()) || COMPOSED.load(Ordering::Relaxed) {
        return delay_conv3x3_composed(x, weight, bias, dilation);
    }
    let [b, t, c, h, w] = x.dims();
    let co = weight.dims()[0];
    let items = x.reshape([b * t, c, h, w]); // [B·T, C_in, H, W]
    let geometry = DelayGeometry { bins: t, dilation };
    let out = <Dispatch as DelayConvBackend>::delay_conv3x3(items.into_dispatch(), weight.into_dispatch(), bias.into_dispatch(), geometry);
    Tensor::<4>::from_dispatch(out).reshape([b, t, co, h, w])
}

/// Whether [`delay_conv3x3`] runs its composed form on the CPU too ([`use_composed`]).
static COMPOSED: AtomicBool = AtomicBool::new(false);

/// Forward passes run on the kernels so far (process-wide), so a test can tell which path ran.
static KERNEL_CALLS: AtomicU64 = AtomicU64::new(0);

/// How many forward passes of [`delay_conv3x3`] the kernels have run in this process.
pub fn kernel_calls() -> u64 {
    KERNEL_CALLS.load(Ordering::Relaxed)
}

/// Make [`delay_conv3x3`] run [`delay_conv3x3_composed`] on every device (`true`) or the kernels
/// on the CPU (`false`, the default), process-wide: for `bench train --delay-path composed`
/// and the tests that compare a training run on either path.
pub fn use_composed(on: bool) {
    COMPOSED.store(on, Ordering::Relaxed);
}

/// [`delay_conv3x3`] composed from burn ops: [`delay_taps`], then a 3×3 convolution over
/// `[B·T, 3·C_in, H, W]` (what every device runs off the CPU).
///
/// # Shapes
/// - `x`: `[B, T, C_in, H, W]`, `weight`: `[C_out, 3·C_in, 3, 3]`, `bias`: `[C_out]` →
///   `[B, T, C_out, H, W]`
pub fn delay_conv3x3_composed(x: Tensor<5>, weight: Tensor<4>, bias: Tensor<1>, dilation: usize) -> Tensor<5> {
    let [b, t, c, h, w] = x.dims();
    let taps = delay_taps(x, dilation).reshape([b * t, 3 * c, h, w]); // [B·T, 3C, H, W]
    let out = conv3x3(taps, weight, bias); // [B·T, C_out, H, W]
    let co = out.dims()[1];
    out.reshape([b, t, co, h, w])
}

/// A burn `Conv2d` layer with a `[C_out, 3·C_in, 3, 3]` kernel as a delay-tap convolution
/// ([`delay_conv3x3`]); zeros for a missing bias.
///
/// # Shapes
/// - `x`: `[B, T, C_in, H, W]` → `[B, T, C_out, H, W]`
pub fn delay_conv3x3_layer(layer: &burn::nn::conv::Conv2d, x: Tensor<5>, dilation: usize) -> Tensor<5> {
    let bias = match &layer.bias {
        Some(b) => b.val(),
        None => Tensor::zeros([layer.weight.dims()[0]], &x.device()),
    };
    delay_conv3x3(x, layer.weight.val(), bias, dilation)
}

/// The circular axis of a delay-tap convolution: `T` bins, dilation `d`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DelayGeometry {
    /// Bins `T`.
    pub bins: usize,
    /// Dilation `d` in `t`.
    pub dilation: usize,
}

/// The backend extension: the forward op and its two gradient ops (the bias gradient is the
/// 3×3 convolution's).
#[backend_extension(Flex, Autodiff)]
pub trait DelayConvBackend: Backend {
    /// `[B·T, C_in, H, W]`, `[C_out, 3·C_in, 3, 3]`, `[C_out]` → `[B·T, C_out, H, W]`
    fn delay_conv3x3(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        geometry: DelayGeometry,
    ) -> FloatTensor<Self>;
    /// Output gradient `[B·T, C_out, H, W]`, `weight` → input gradient `[B·T, C_in, H, W]`
    fn delay_conv3x3_x_backward(grad: FloatTensor<Self>, weight: FloatTensor<Self>, geometry: DelayGeometry) -> FloatTensor<Self>;
    /// Input `[B·T, C_in, H, W]`, output gradient `[B·T, C_out, H, W]` → kernel gradient `[C_out, 3·C_in, 3, 3]`
    fn delay_conv3x3_w_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>, geometry: DelayGeometry) -> FloatTensor<Self>;
}

/// The slice kernel's sizes for items `[B·T, C_in, H, W]` and `C_out` outputs.
fn sizes([bt, c_in, h, w]: [usize; 4], c_out: usize, g: DelayGeometry) -> DelayConv3x3 {
    assert!(g.bins > 0 && bt % g.bins == 0, "delay conv: {bt} frames are not whole cubes of {} bins", g.bins);
    DelayConv3x3 { batch: bt / g.bins, bins: g.bins, c_in, c_out, height: h, width: w, dilation: g.dilation }
}

fn from_vec(v: Vec<f32>, shape: [usize; 4]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(v, Shape::from(shape)))
}

impl DelayConvBackend for Flex {
    fn delay_conv3x3(x: FlexTensor, weight: FlexTensor, bias: FlexTensor, g: DelayGeometry) -> FlexTensor {
        let dims = dims4(&x);
        let [co, wci, kh, kw] = dims4(&weight);
        assert!(wci == 3 * dims[1] && kh == 3 && kw == 3, "delay conv: kernel {:?} for input {dims:?}", [co, wci, kh, kw]);
        KERNEL_CALLS.fetch_add(1, Ordering::Relaxed);
        let dtype = x.dtype();
        let (x, weight, bias) = (to_f32(x), to_f32(weight), to_f32(bias));
        let d = sizes(dims, co, g);
        let mut y = vec![0.0f32; d.y_len()];
        d.forward(f32_slice(&x), f32_slice(&weight), Some(f32_slice(&bias)), &mut y);
        like(from_vec(y, [dims[0], co, dims[2], dims[3]]), dtype)
    }

    fn delay_conv3x3_x_backward(grad: FlexTensor, weight: FlexTensor, g: DelayGeometry) -> FlexTensor {
        let [bt, co, h, w] = dims4(&grad);
        let [wco, k3, _, _] = dims4(&weight);
        assert_eq!(wco, co, "delay conv x backward: kernel and gradient channels");
        let dtype = grad.dtype();
        let (grad, weight) = (to_f32(grad), to_f32(weight));
        let d = sizes([bt, k3 / 3, h, w], co, g);
        let mut dx = vec![0.0f32; d.x_len()];
        d.backward_x(f32_slice(&grad), f32_slice(&weight), &mut dx);
        like(from_vec(dx, [bt, k3 / 3, h, w]), dtype)
    }

    fn delay_conv3x3_w_backward(x: FlexTensor, grad: FlexTensor, g: DelayGeometry) -> FlexTensor {
        let dims = dims4(&x);
        let co = dims4(&grad)[1];
        let dtype = x.dtype();
        let (x, grad) = (to_f32(x), to_f32(grad));
        let d = sizes(dims, co, g);
        let mut dw = vec![0.0f32; d.w_len()];
        d.backward_w(f32_slice(&x), f32_slice(&grad), &mut dw);
        like(from_vec(dw, [co, 3 * dims[1], 3, 3]), dtype)
    }
}

/// `t` as a contiguous f32 tensor (the kernels compute in f32 whatever the dtype; a copy only
/// when `t` is strided or of another dtype).
fn to_f32(t: FlexTensor) -> FlexTensor {
    match f32_contiguous(t.clone()) {
        Some(c) => c,
        None => Flex::float_cast(t, FloatDType::F32).to_contiguous(),
    }
}

/// `t` (f32) cast back to the float dtype of the op's input.
fn like(t: FlexTensor, dtype: DType) -> FlexTensor {
    if dtype == DType::F32 {
        t
    } else {
        Flex::float_cast(t, dtype.into())
    }
}

/// The backward step of [`delay_conv3x3`]: parents `[x, weight, bias]`, state `(x, weight, geometry)`.
#[derive(Debug)]
struct DelayConvStep;

impl<B: Backend + DelayConvBackend + Conv3x3Backend> Backward<B, 3> for DelayConvStep {
    type State = (FloatTensor<B>, FloatTensor<B>, DelayGeometry);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_x, node_w, node_b] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, g) = ops.state;
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::delay_conv3x3_x_backward(grad.clone(), weight, g));
        }
        if let Some(node) = node_w {
            grads.register::<B>(node.id, B::delay_conv3x3_w_backward(x, grad.clone(), g));
        }
        if let Some(node) = node_b {
            grads.register::<B>(node.id, B::conv3x3_bias_backward(grad));
        }
    }
}

impl<B: Backend + DelayConvBackend + Conv3x3Backend, C: CheckpointStrategy> DelayConvBackend for Autodiff<B, C> {
    fn delay_conv3x3(x: FloatTensor<Self>, weight: FloatTensor<Self>, bias: FloatTensor<Self>, g: DelayGeometry) -> FloatTensor<Self> {
        match DelayConvStep.prepare::<C>([x.node(), weight.node(), bias.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let state = (x.primitive().clone(), weight.primitive().clone(), g);
                prep.finish(state, B::delay_conv3x3(x.into_primitive(), weight.into_primitive(), bias.into_primitive(), g))
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::delay_conv3x3(x.into_primitive(), weight.into_primitive(), bias.into_primitive(), g))
            }
        }
    }

    // Used inside backward passes only: constants to autodiff (first order).
    fn delay_conv3x3_x_backward(grad: FloatTensor<Self>, weight: FloatTensor<Self>, g: DelayGeometry) -> FloatTensor<Self> {
        Self::from_inner(B::delay_conv3x3_x_backward(Self::inner(grad), Self::inner(weight), g))
    }

    fn delay_conv3x3_w_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>, g: DelayGeometry) -> FloatTensor<Self> {
        Self::from_inner(B::delay_conv3x3_w_backward(Self::inner(x), Self::inner(grad), g))
    }
}
