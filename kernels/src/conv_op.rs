//! [`conv3x3`]: the 3×3 convolution of the ADMM-Net prior as a burn backend extension, so that
//! both the forward pass and the handwritten backward pass run the im2col + GEMM kernels of
//! [`crate::conv`] instead of burn-flex's generic convolution (whose weight gradient was 40 %
//! of a training step).
//!
//! ```text
//! Tensor<4> ──into_dispatch──▶ Dispatch ──▶ Flex               (inference: kernels only)
//!                                      └──▶ Autodiff<Flex, C>   (training: kernels + Backward)
//! ```
//!
//! On another device than `Flex` or `Autodiff<Flex>` (the GPU build) it is burn's own `conv2d`
//! ([`crate::runs_kernels`]). Tensors of another float type than `f32` fall back to burn's own
//! conv too.

use burn::backend::autodiff::checkpoint::{base::Checkpointer, strategy::CheckpointStrategy};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::{Flex, FlexTensor};
use burn::backend::ops::{ConvOptions, FloatTensorOps, ModuleOps};
use burn::backend::tensor::FloatTensor;
use burn::backend::{backend_extension, Autodiff, AutodiffBackend, Backend, Dispatch};
use burn::tensor::{DType, Shape, Tensor, TensorData};

use crate::conv::Conv3x3;

/// 3×3 "same" convolution: stride 1, zero padding 1, with bias.
///
/// # Shapes
/// - `x`: `[B, C_in, H, W]`, `weight`: `[C_out, C_in, 3, 3]`, `bias`: `[C_out]` → `[B, C_out, H, W]`
pub fn conv3x3(x: Tensor<4>, weight: Tensor<4>, bias: Tensor<1>) -> Tensor<4> {
    if !crate::runs_kernels(&x.device()) {
        return burn::tensor::module::conv2d(x, weight, Some(bias), options());
    }
    let out = <Dispatch as Conv3x3Backend>::conv3x3(x.into_dispatch(), weight.into_dispatch(), bias.into_dispatch());
    Tensor::from_dispatch(out)
}

/// A burn `Conv2d` layer with a 3×3 kernel (stride 1, "same" padding) through [`conv3x3`]:
/// its weight and bias (zeros when it has none).
///
/// # Shapes
/// - `x`: `[B, C_in, H, W]` → `[B, C_out, H, W]`
pub fn conv3x3_layer(layer: &burn::nn::conv::Conv2d, x: Tensor<4>) -> Tensor<4> {
    let bias = match &layer.bias {
        Some(b) => b.val(),
        None => Tensor::zeros([layer.weight.dims()[0]], &x.device()),
    };
    conv3x3(x, layer.weight.val(), bias)
}

/// The backend extension: the forward op and the two gradient ops it needs.
#[backend_extension(Flex, Autodiff)]
pub trait Conv3x3Backend: Backend {
    /// `[B, C_in, H, W]`, `[C_out, C_in, 3, 3]`, `[C_out]` → `[B, C_out, H, W]`
    fn conv3x3(x: FloatTensor<Self>, weight: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Output gradient `[B, C_out, H, W]`, `weight` → input gradient `[B, C_in, H, W]`
    fn conv3x3_x_backward(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Input `[B, C_in, H, W]`, output gradient `[B, C_out, H, W]` → kernel gradient `[C_out, C_in, 3, 3]`
    fn conv3x3_w_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self>;
    /// Output gradient `[B, C_out, H, W]` → bias gradient `[C_out]`
    fn conv3x3_bias_backward(grad: FloatTensor<Self>) -> FloatTensor<Self>;
}

fn options() -> ConvOptions<2> {
    ConvOptions::new([1, 1], [1, 1], [1, 1], 1)
}

/// The shape of a rank-4 tensor (the custom ops of this crate take no other).
pub(crate) fn dims4(t: &FlexTensor) -> [usize; 4] {
    let s = t.layout().shape();
    assert_eq!(s.num_dims(), 4, "expected a rank-4 tensor, got {s:?}");
    [s[0], s[1], s[2], s[3]]
}

/// Run `f` on a contiguous f32 view of `t` and its shape (copying only when `t` is strided or
/// not f32).
pub(crate) fn with_f32<R>(t: FlexTensor, f: impl FnOnce(&[f32], [usize; 4]) -> R) -> R {
    let dims = dims4(&t);
    match f32_contiguous(t.clone()) {
        Some(c) => f(f32_slice(&c), dims),
        None => f(&t.into_data().convert::<f32>().try_into_vec::<f32>().expect("converted to f32"), dims),
    }
}

/// A contiguous `f32` view of `t` (copying only when it is strided), or `None` for other dtypes.
pub(crate) fn f32_contiguous(t: FlexTensor) -> Option<FlexTensor> {
    if t.dtype() != DType::F32 {
        return None;
    }
    Some(if t.as_slice::<f32>().is_some() { t } else { t.to_contiguous() })
}

pub(crate) fn f32_slice(t: &FlexTensor) -> &[f32] {
    t.as_slice::<f32>().expect("f32_contiguous returned a contiguous f32 tensor")
}

fn from_vec(v: Vec<f32>, shape: [usize; 4]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(v, Shape::from(shape)))
}

impl Conv3x3Backend for Flex {
    fn conv3x3(x: FlexTensor, weight: FlexTensor, bias: FlexTensor) -> FlexTensor {
        let [b, ci, h, w] = dims4(&x);
        let [co, wci, kh, kw] = dims4(&weight);
        assert!(wci == ci && kh == 3 && kw == 3, "conv3x3: kernel {:?} for input {:?}", [co, wci, kh, kw], [b, ci, h, w]);
        match (f32_contiguous(x.clone()), f32_contiguous(weight.clone()), f32_contiguous(bias.clone())) {
            (Some(x), Some(weight), Some(bias)) => {
                let d = Conv3x3 { batch: b, c_in: ci, c_out: co, height: h, width: w };
                let mut y = vec![0.0f32; d.y_len()];
                d.forward(f32_slice(&x), f32_slice(&weight), Some(f32_slice(&bias)), &mut y);
                from_vec(y, [b, co, h, w])
            }
            _ => Flex::conv2d(x, weight, Some(bias), options()),
        }
    }

    fn conv3x3_x_backward(grad: FlexTensor, weight: FlexTensor) -> FlexTensor {
        let [b, co, h, w] = dims4(&grad);
        let [wco, ci, _, _] = dims4(&weight);
        assert_eq!(wco, co, "conv3x3_x_backward: kernel and gradient channels");
        let (grad, weight) = match (f32_contiguous(grad.clone()), f32_contiguous(weight.clone())) {
            (Some(g), Some(k)) => (g, k),
            _ => {
                let x = Flex::float_zeros(Shape::from([b, ci, h, w]), &Default::default(), grad.dtype().into());
                return Flex::conv2d_x_backward(x, weight, grad, options());
            }
        };
        let d = Conv3x3 { batch: b, c_in: ci, c_out: co, height: h, width: w };
        let mut dx = vec![0.0f32; d.x_len()];
        d.backward_x(f32_slice(&grad), f32_slice(&weight), &mut dx);
        from_vec(dx, [b, ci, h, w])
    }

    fn conv3x3_w_backward(x: FlexTensor, grad: FlexTensor) -> FlexTensor {
        let [b, ci, h, w] = dims4(&x);
        let [_, co, _, _] = dims4(&grad);
        let (x, grad) = match (f32_contiguous(x.clone()), f32_contiguous(grad.clone())) {
            (Some(x), Some(g)) => (x, g),
            _ => {
                let k = Flex::float_zeros(Shape::from([co, ci, 3, 3]), &Default::default(), x.dtype().into());
                return Flex::conv2d_weight_backward(x, k, grad, options());
            }
        };
        let d = Conv3x3 { batch: b, c_in: ci, c_out: co, height: h, width: w };
        let mut dw = vec![0.0f32; d.w_len()];
        d.backward_w(f32_slice(&x), f32_slice(&grad), &mut dw);
        from_vec(dw, [co, ci, 3, 3])
    }

    fn conv3x3_bias_backward(grad: FlexTensor) -> FlexTensor {
        let [b, co, h, w] = dims4(&grad);
        let Some(grad) = f32_contiguous(grad.clone()) else {
            // Σ over batch, rows and columns in the tensor's own dtype
            let g = Flex::float_reshape(grad, Shape::from([b, co, h * w]));
            return Flex::float_reshape(Flex::float_sum_dim(Flex::float_sum_dim(g, 2), 0), Shape::from([co]));
        };
        let d = Conv3x3 { batch: b, c_in: 0, c_out: co, height: h, width: w };
        let mut db = vec![0.0f32; co];
        d.backward_bias(f32_slice(&grad), &mut db);
        FlexTensor::from_data(TensorData::new(db, Shape::from([co])))
    }
}

/// The backward step of [`conv3x3`]: parents `[x, weight, bias]`, state `(x, weight)`.
#[derive(Debug)]
struct Conv3x3Step;

impl<B: Backend + Conv3x3Backend> Backward<B, 3> for Conv3x3Step {
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let [node_x, node_w, node_b] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight) = ops.state;
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::conv3x3_x_backward(grad.clone(), weight));
        }
        if let Some(node) = node_w {
            grads.register::<B>(node.id, B::conv3x3_w_backward(x, grad.clone()));
        }
        if let Some(node) = node_b {
            grads.register::<B>(node.id, B::conv3x3_bias_backward(grad));
        }
    }
}

impl<B: Backend + Conv3x3Backend, C: CheckpointStrategy> Conv3x3Backend for Autodiff<B, C> {
    fn conv3x3(x: FloatTensor<Self>, weight: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        match Conv3x3Step.prepare::<C>([x.node(), weight.node(), bias.node()]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let state = (x.primitive().clone(), weight.primitive().clone());
                prep.finish(state, B::conv3x3(x.into_primitive(), weight.into_primitive(), bias.into_primitive()))
            }
            OpsKind::UnTracked(prep) => prep.finish(B::conv3x3(x.into_primitive(), weight.into_primitive(), bias.into_primitive())),
        }
    }

    // The gradient ops are used inside backward passes only; as autodiff ops they are
    // constants (first-order autodiff).
    fn conv3x3_x_backward(grad: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::from_inner(B::conv3x3_x_backward(Self::inner(grad), Self::inner(weight)))
    }

    fn conv3x3_w_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::from_inner(B::conv3x3_w_backward(Self::inner(x), Self::inner(grad)))
    }

    fn conv3x3_bias_backward(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::from_inner(B::conv3x3_bias_backward(Self::inner(grad)))
    }
}
