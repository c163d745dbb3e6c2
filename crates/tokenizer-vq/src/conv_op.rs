//! The im2col convolution as one autodiff operation that keeps only its input and weight.
//!
//! Differentiated op by op, the matrix-product convolution would keep its columns (`kh·kw` copies of the
//! input) until the backward pass: about 2.4 GB for each full-resolution 3×3 convolution of the `small`
//! map tokenizer at batch 16, tens of GB per step. This operation rebuilds them in the backward pass
//! instead, where the weight gradient is `dy · colsᵀ`. The input gradient of a stride-1 convolution is the
//! convolution of `dy` with the flipped, transposed kernel (gathered like the forward pass, which the
//! profile showed cheaper than folding: no copy of the padded input per tap); strided convolutions fold
//! `Wᵀ · dy` back onto the input ([`fold`]).
//!
//! Dispatch mirrors the backbone's tiled attention: the model is generic over `B: Backend`, so the
//! training backends that take this operation are recognised by comparing function-pointer types through
//! `Any`.

use crate::conv::{Geometry, columns, fold, product};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};
use std::any::Any;

/// A bias-free convolution `(input, weight, geometry) → output` on backend `B`.
pub type ConvFn<B> = fn(Tensor<B, 4>, Tensor<B, 4>, Geometry) -> Tensor<B, 4>;

/// The operation on `B` when `B` is a CUDA training backend (either checkpointing strategy); `None`
/// otherwise.
pub fn gemm_autodiff_for<B: Backend>() -> Option<ConvFn<B>> {
    #[cfg(feature = "cuda")]
    {
        on::<B, burn::backend::Cuda>()
    }
    #[cfg(not(feature = "cuda"))]
    {
        None
    }
}

#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
fn on<B: Backend, I: Backend>() -> Option<ConvFn<B>> {
    fn cast<B: Backend, A: Backend>(f: ConvFn<A>) -> Option<ConvFn<B>> {
        (&f as &dyn Any).downcast_ref::<ConvFn<B>>().copied()
    }
    cast::<B, Autodiff<I, NoCheckpointing>>(gemm_autodiff::<I, NoCheckpointing>)
        .or_else(|| cast::<B, Autodiff<I, BalancedCheckpointing>>(gemm_autodiff::<I, BalancedCheckpointing>))
}

fn float<B: Backend, const D: usize>(t: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

#[derive(Debug)]
struct GemmConv;

impl<B: Backend> Backward<B, 2> for GemmConv {
    /// Input, weight, geometry.
    type State = (FloatTensor<B>, FloatTensor<B>, Geometry);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_x, node_w] = ops.parents;
        let dy = float::<B, 4>(grads.consume::<B>(&ops.node));
        let (x, w, g) = ops.state;
        let (x, w) = (float::<B, 4>(x), float::<B, 4>(w));
        let [o, c, kh, kw] = w.dims();
        let ([b, ..], [ho, wo]) = (g.input(), g.output());
        let dy = dy.reshape([b, o, ho * wo]);
        if let Some(node) = node_w {
            let cols = columns(x, &g);
            let dw = dy
                .clone()
                .matmul(cols.swap_dims(1, 2))
                .sum_dim(0)
                .reshape([o, c, kh, kw]);
            grads.register::<B>(node.id, dw.into_primitive().tensor());
        }
        if let Some(node) = node_x {
            let dx = match g.transposed(o) {
                // Stride 1: a convolution of dy with the flipped kernel, gathered like the forward pass.
                Some(gt) => product(
                    w.swap_dims(0, 1).flip([2, 3]),
                    columns(dy.reshape([b, o, ho, wo]), &gt),
                    &gt,
                ),
                None => {
                    let k = c * kh * kw;
                    let wt = w.reshape([o, k]).transpose().unsqueeze::<3>().expand([b, k, o]);
                    fold(wt.matmul(dy), &g)
                }
            };
            grads.register::<B>(node.id, dx.into_primitive().tensor());
        }
    }
}

/// The convolution on `Autodiff<I, C>` without a bias: forward through the columns on the inner backend,
/// keeping only `x` and `w` for the backward pass.
pub fn gemm_autodiff<I: Backend, C: CheckpointStrategy>(
    x: Tensor<Autodiff<I, C>, 4>,
    w: Tensor<Autodiff<I, C>, 4>,
    g: Geometry,
) -> Tensor<Autodiff<I, C>, 4> {
    let (x, w) = (x.into_primitive().tensor(), w.into_primitive().tensor());
    let prep = GemmConv
        .prepare::<C>([x.node.clone(), w.node.clone()])
        .compute_bound()
        .stateful();
    let (xi, wi) = (float::<I, 4>(x.primitive), float::<I, 4>(w.primitive));
    let y = product(wi.clone(), columns(xi.clone(), &g), &g)
        .into_primitive()
        .tensor();
    let y = match prep {
        OpsKind::Tracked(prep) => {
            prep.finish((xi.into_primitive().tensor(), wi.into_primitive().tensor(), g), y)
        }
        OpsKind::UnTracked(prep) => prep.finish(y),
    };
    float(y)
}
