//! An MLP's hidden activation, `gelu(x · W + b)`, with the bias and GELU as one operation ([`linear_gelu`]).
//!
//! Through burn's operations an MLP's first layer is the product, a broadcast bias add and GELU, which
//! burn-fusion runs as one element-wise kernel writing the activation in f32 (and keeping the
//! pre-activation for the backward pass), then a cast to bf16 for the next product; the backward pass is
//! GELU's derivative, the bias's row sums and another cast. In the `small` preset's timeline
//! (docs/decisions/007-memory-bound-training-kernels.md) those passes over the `[70,368, 1,536]` hidden activations were the largest family
//! of kernel time: twenty kernels of 0.7–0.78 ms and casts of 0.23 ms. On the training backends
//! [`linear_gelu`] is instead the product (without its bias, written in the next product's format: bf16
//! with the bf16 presets, as PyTorch's autocast writes it) followed by a custom autodiff operation whose
//! passes are [`FusedGelu`]'s: on CUDA one kernel each (umgen-cuda's `kernels/train/gelu.cu`), the forward pass reading the
//! product once and writing the activation in its format, the backward pass recomputing the
//! pre-activation and writing its gradient (in that format too) with the bias's gradient summed in f32; on
//! the CPU the same arithmetic as burn operations ([`forward_decomposed`], [`backward_decomposed`]). The
//! operation keeps the product, as burn's GELU keeps its input; the bias is added and GELU computed in f32.
//!
//! Both passes use GELU's exact form (erf) and its exact derivative, `Φ(x) + x·φ(x)`, as PyTorch's
//! `nn.GELU()` does; burn's own backward pass uses the tanh approximation's derivative, which
//! `train.kernels.gelu = "burn"` keeps.

#[cfg(feature = "cuda")]
mod cuda;

use crate::dispatch::{Fallbacks, same};
use crate::format::Precision;
use crate::format::float;
use crate::format::float_format;
pub use crate::kernels::GeluKernel;
use crate::kernels::Kernels;
use crate::linear::linear;
use crate::matmul::Written;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::nn::Linear;
use burn::tensor::activation::gelu;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{FloatDType, Tensor, TensorPrimitive};

/// Passes the kernels refused in this process.
static FALLBACKS: Fallbacks = Fallbacks::new("bias + GELU");

/// How many bias + GELU passes fell back from the CUDA kernels to burn's operations in this process.
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}

/// Counts a pass the kernels refused for `why`; logs the first.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
fn fell_back(why: &str) {
    FALLBACKS.fell_back(why);
}

/// A backend that computes an MLP's bias + GELU over the rows of `[rows, n]` products (f32 or bf16; the
/// results are written in the product's format, the arithmetic is f32). The passes default to burn's
/// operations ([`forward_decomposed`], [`backward_decomposed`]); CUDA overrides them.
pub trait FusedGelu: Backend {
    /// `gelu(y + b)` row by row, in `y`'s format.
    fn bias_gelu_forward(y: Tensor<Self, 2>, b: Tensor<Self, 1>) -> Tensor<Self, 2> {
        forward_decomposed(y, b)
    }

    /// The gradient of the pre-activation, `dh · gelu'(y + b)` (in `y`'s format), and the bias's (f32, its
    /// column sums), from the activation's gradient `dh` (either format).
    fn bias_gelu_backward(
        dh: Tensor<Self, 2>,
        y: Tensor<Self, 2>,
        b: Tensor<Self, 1>,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>) {
        backward_decomposed(dh, y, b)
    }
}

/// The CPU backend computes the decomposition.
impl FusedGelu for burn::backend::Flex {}

/// [`FusedGelu::bias_gelu_forward`] as burn operations.
pub fn forward_decomposed<B: Backend>(y: Tensor<B, 2>, b: Tensor<B, 1>) -> Tensor<B, 2> {
    let out = float_format(y.dtype());
    gelu(y.cast(FloatDType::F32) + b.unsqueeze::<2>()).cast(out)
}

/// [`FusedGelu::bias_gelu_backward`] as burn operations (GELU's exact derivative).
pub fn backward_decomposed<B: Backend>(
    dh: Tensor<B, 2>,
    y: Tensor<B, 2>,
    b: Tensor<B, 1>,
) -> (Tensor<B, 2>, Tensor<B, 1>) {
    let out = float_format(y.dtype());
    let x = y.cast(FloatDType::F32) + b.unsqueeze::<2>();
    let cdf = x
        .clone()
        .div_scalar(std::f64::consts::SQRT_2)
        .erf()
        .add_scalar(1.0)
        .mul_scalar(0.5);
    let pdf = x
        .clone()
        .powi_scalar(2)
        .mul_scalar(-0.5)
        .exp()
        .mul_scalar(0.398_942_280_401_432_7);
    let d = dh.cast(FloatDType::F32) * (cdf + x * pdf);
    let db = crate::rows::sum(d.clone());
    (d.cast(out), db)
}

/// `gelu(layer.forward(x))` with the product in `p`'s format, the product and the result in the products'
/// operand format ([`Precision::operand_dtype`], so that the next product needs no cast) where the training
/// backends run it as one operation (a layer with a bias, the named matmul, and [`GeluKernel::Fused`]);
/// elsewhere burn's operations in f32.
pub fn linear_gelu<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    k: &Kernels,
) -> Tensor<B, D> {
    let (Some(product), Some(op), Some(bias)) =
        (crate::matmul::named_for::<B>(k), tracked::<B>(k), &layer.bias)
    else {
        return gelu(linear(layer, x, p, k));
    };
    let format = p.operand_dtype();
    let written = Written {
        out: format,
        dx: FloatDType::F32,
    };
    let (y, dims) = crate::linear::product_rows(product, x, layer.weight.val(), p, written, k);
    op(y, bias.val()).reshape(dims)
}

/// The format of the MLP's first product where [`inner_forward`] reads it: the activation's
/// (the products' operand format, [`Precision::operand_dtype`]) for [`GeluKernel::Fused`], f32 for burn's
/// operations.
pub(crate) fn inner_product_dtype(p: Precision, k: &Kernels) -> FloatDType {
    match k.gelu {
        GeluKernel::Fused => p.operand_dtype(),
        GeluKernel::Burn => FloatDType::F32,
    }
}

/// The passes on a backend without autodiff, as [`linear_gelu`] runs them for `k.gelu`: the
/// activation from the product `y` (without its bias, in [`inner_product_dtype`]).
/// `layer/math.rs`'s hand-written layer uses them.
pub(crate) fn inner_forward<I: FusedGelu>(y: Tensor<I, 2>, b: Tensor<I, 1>, k: &Kernels) -> Tensor<I, 2> {
    match k.gelu {
        GeluKernel::Fused => I::bias_gelu_forward(y, b),
        GeluKernel::Burn => gelu(y.cast(FloatDType::F32) + b.unsqueeze::<2>()),
    }
}

/// [`inner_forward`]'s gradients: the pre-activation's (in `y`'s format) and the bias's, from the
/// activation's `dh`.
pub(crate) fn inner_backward<I: FusedGelu>(
    dh: Tensor<I, 2>,
    y: Tensor<I, 2>,
    b: Tensor<I, 1>,
    k: &Kernels,
) -> (Tensor<I, 2>, Tensor<I, 1>) {
    match k.gelu {
        GeluKernel::Fused => I::bias_gelu_backward(dh, y, b),
        GeluKernel::Burn => {
            let x = y.cast(FloatDType::F32) + b.unsqueeze::<2>();
            let d = float::<I, 2>(I::gelu_backward(
                x.into_primitive().tensor(),
                dh.cast(FloatDType::F32).into_primitive().tensor(),
            ));
            (d.clone(), crate::rows::sum(d))
        }
    }
}

/// The operation on `B`: the product `[rows, n]` and the bias in, `[rows, n]` out (in the product's format).
pub(crate) type GeluOp<B> = fn(Tensor<B, 2>, Tensor<B, 1>) -> Tensor<B, 2>;

/// The custom operation when `B` is a training backend and `k` chooses [`GeluKernel::Fused`].
pub(crate) fn tracked<B: Backend>(k: &Kernels) -> Option<GeluOp<B>> {
    if k.gelu == GeluKernel::Burn {
        return None;
    }
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(|| on::<B, burn::backend::Cuda>());
    found
}

/// The operation on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: FusedGelu>() -> Option<GeluOp<B>> {
    let plain: GeluOp<Autodiff<I>> = apply::<I, NoCheckpointing>;
    let balanced: GeluOp<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass of the operation.
#[derive(Debug)]
struct BiasGelu;

impl<I: FusedGelu> Backward<I, 2> for BiasGelu {
    /// The product and the bias.
    type State = (FloatTensor<I>, FloatTensor<I>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dh = float::<I, 2>(grads.consume::<I>(&ops.node));
        let (y, b) = ops.state;
        let (dy, db) = I::bias_gelu_backward(dh, float(y), float(b));
        let [y_node, b_node] = ops.parents;
        if let Some(node) = y_node {
            grads.register::<I>(node.id, dy.into_primitive().tensor());
        }
        if let Some(node) = b_node {
            grads.register::<I>(node.id, db.into_primitive().tensor());
        }
    }
}

/// `gelu(y + b)` of `[rows, n]` in `y`'s format as one operation on `Autodiff<I, C>`.
fn apply<I: FusedGelu, C: CheckpointStrategy>(
    y: Tensor<Autodiff<I, C>, 2>,
    b: Tensor<Autodiff<I, C>, 1>,
) -> Tensor<Autodiff<I, C>, 2> {
    let (y, b) = (y.into_primitive().tensor(), b.into_primitive().tensor());
    let h = I::bias_gelu_forward(float(y.primitive.clone()), float(b.primitive.clone()));
    let h = h.into_primitive().tensor();
    let result = match BiasGelu
        .prepare::<C>([y.node.clone(), b.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish((y.primitive.clone(), b.primitive.clone()), h),
        OpsKind::UnTracked(prep) => prep.finish(h),
    };
    Tensor::from_primitive(TensorPrimitive::Float(result))
}

#[cfg(test)]
mod tests;
