//! Layer norm as one operation with a hand-written backward pass ([`layer_norm`]).
//!
//! burn's `LayerNorm` is a decomposition (mean, centred variance, normalisation, scale, shift), and its
//! autodiff keeps the intermediate tensors and runs a backward kernel for each step. In a profiled `small`
//! step on an H100 (docs/decisions/007-memory-bound-training-kernels.md) one layer norm of a `[70,368, 384]` activation took 8 kernels and
//! about 0.7 ms forward, where reading the input once and writing the output takes 0.08 ms; the step has
//! 26 of them. On the training backends [`layer_norm`] is instead a custom autodiff operation whose passes
//! are [`FusedNorm`]'s: on CUDA, one kernel each (umgen-cuda's `kernels/train/norm.cu`, one warp a row); on the CPU, the same
//! decomposition ([`forward_decomposed`], [`backward_decomposed`]), which CUDA also runs for
//! rows over 1,024 wide (counted by [`fallbacks`]). The operation keeps only its
//! input, the rows' means and `1/σ`; where its output feeds products, the input in their format
//! (`train.kernels.kept_inputs`). Where the output feeds
//! products only, [`layer_norm_operand`] writes it in the products' format (bf16 under mixed precision),
//! so that no f32 copy is written and cast.

#[cfg(feature = "cuda")]
mod cuda;

use crate::dispatch::{Fallbacks, same};
use crate::format::float;
use crate::kernels::Kernels;
pub use crate::kernels::NormKernel;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::nn::LayerNorm;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, FloatDType, Tensor};

/// Passes the kernels refused in this process.
static FALLBACKS: Fallbacks = Fallbacks::new("layer-norm");

/// How many layer-norm passes fell back from the CUDA kernels to the decomposition in this process.
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}

/// Counts a pass the kernels refused for `why`; logs the first.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
fn fell_back(why: &str) {
    FALLBACKS.fell_back(why);
}

/// ε of every layer norm the backbone builds (`LayerNormConfig::new`'s default; burn keeps the field
/// private, and a test checks the two agree).
pub const LN_EPS: f64 = 1e-5;

/// A layer norm's forward pass: the output, the rows' statistics for the backward pass and, where asked
/// for, the input in the format the backward pass keeps it in.
#[derive(Debug, Clone)]
pub struct Normed<B: Backend> {
    /// `[rows, d]`, in the format asked for.
    pub y: Tensor<B, 2>,
    /// The rows' means, `[rows]`, f32.
    pub mean: Tensor<B, 1>,
    /// The rows' `1/√(var + ε)`, `[rows]`, f32.
    pub rstd: Tensor<B, 1>,
    /// The input in the kept format, where one was asked for.
    pub kept: Option<Tensor<B, 2>>,
}

/// A backend that computes a layer norm's two passes over the rows of `[rows, d]` matrices. The input is
/// f32 or a bf16 copy kept for the backward pass (read as its exact f32 value). The passes default to
/// burn's operations ([`forward_decomposed`], [`backward_decomposed`]); CUDA overrides them.
pub trait FusedNorm: Backend {
    /// `(x − mean) / √(var + ε) · γ + β` row by row (centred variance) in `out`'s format, with each
    /// row's mean and `1/√(var + ε)` (`[rows]`, f32) for the backward pass, and with `keep`, `x` in that
    /// format (on CUDA written by the same kernel as it reads `x`, instead of a cast reading it again).
    fn norm_forward(
        x: Tensor<Self, 2>,
        gamma: Tensor<Self, 1>,
        beta: Tensor<Self, 1>,
        eps: f64,
        (out, keep): (FloatDType, Option<FloatDType>),
        k: &Kernels,
    ) -> Normed<Self> {
        let _ = k;
        forward_decomposed(x, gamma, beta, eps, (out, keep))
    }

    /// The gradients of the input, the scale and the shift from the output's gradient `dy`, given the
    /// forward pass's input (f32 or its kept copy), means and `1/σ`. With `dres` (f32, the input's shape),
    /// the input's gradient is that plus the norm's: what a pre-norm layer's residual stream brings to the
    /// same input, added as the gradient is written (on CUDA in the same kernel).
    fn norm_backward(
        dy: Tensor<Self, 2>,
        (x, mean, rstd): (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>),
        gamma: Tensor<Self, 1>,
        dres: Option<Tensor<Self, 2>>,
        k: &Kernels,
    ) -> (Tensor<Self, 2>, Tensor<Self, 1>, Tensor<Self, 1>) {
        let _ = k;
        let (dx, dgamma, dbeta) = backward_decomposed(dy, x, mean, rstd, gamma);
        (plus(dx, dres), dgamma, dbeta)
    }
}

/// [`FusedNorm::norm_forward`] as burn operations: the output computed in f32, then cast to `out`'s format;
/// the kept copy cast from the input.
pub fn forward_decomposed<B: Backend>(
    x: Tensor<B, 2>,
    gamma: Tensor<B, 1>,
    beta: Tensor<B, 1>,
    eps: f64,
    (out, keep): (FloatDType, Option<FloatDType>),
) -> Normed<B> {
    let kept = keep.map(|f| x.clone().cast(f));
    let x = x.cast(FloatDType::F32);
    let rows = x.dims()[0];
    let mean = x.clone().mean_dim(1);
    let centered = x - mean.clone();
    let rstd = centered
        .clone()
        .powi_scalar(2)
        .mean_dim(1)
        .add_scalar(eps)
        .sqrt()
        .recip();
    let y = centered * rstd.clone() * gamma.unsqueeze::<2>() + beta.unsqueeze::<2>();
    Normed {
        y: y.cast(out),
        mean: mean.reshape([rows]),
        rstd: rstd.reshape([rows]),
        kept,
    }
}

/// [`FusedNorm::norm_backward`] as burn operations.
pub fn backward_decomposed<B: Backend>(
    dy: Tensor<B, 2>,
    x: Tensor<B, 2>,
    mean: Tensor<B, 1>,
    rstd: Tensor<B, 1>,
    gamma: Tensor<B, 1>,
) -> (Tensor<B, 2>, Tensor<B, 1>, Tensor<B, 1>) {
    let x = x.cast(FloatDType::F32);
    let rstd = rstd.unsqueeze_dim::<2>(1);
    let xhat = (x - mean.unsqueeze_dim::<2>(1)) * rstd.clone();
    let dgamma = crate::rows::sum(dy.clone() * xhat.clone());
    let dbeta = crate::rows::sum(dy.clone());
    let g = dy * gamma.unsqueeze::<2>();
    let dx = (g.clone() - g.clone().mean_dim(1) - xhat.clone() * (g * xhat).mean_dim(1)) * rstd;
    (dx, dgamma, dbeta)
}

/// `dx`, plus `dres` where given.
pub(crate) fn plus<B: Backend>(dx: Tensor<B, 2>, dres: Option<Tensor<B, 2>>) -> Tensor<B, 2> {
    match dres {
        Some(r) => dx + r.cast(FloatDType::F32),
        None => dx,
    }
}

/// The CPU backend computes the decomposition.
impl FusedNorm for burn::backend::Flex {}

/// `ln.forward(x)` over the last axis: on the training backends one operation with [`FusedNorm`]'s
/// passes, elsewhere (inference backends) the decomposition.
pub fn layer_norm<B: Backend, const D: usize>(
    ln: &LayerNorm<B>,
    x: Tensor<B, D>,
    k: &Kernels,
) -> Tensor<B, D> {
    layer_norm_as(ln, x, FloatDType::F32, k)
}

/// [`layer_norm`] for an output that only products read: in their operand format under `p`
/// (`precision::operand` of the f32 norm, written so by the kernel on CUDA).
pub fn layer_norm_operand<B: Backend, const D: usize>(
    ln: &LayerNorm<B>,
    x: Tensor<B, D>,
    p: crate::format::Precision,
    k: &Kernels,
) -> Tensor<B, D> {
    layer_norm_as(ln, x, p.operand_dtype(), k)
}

/// [`layer_norm`] with its output in `out`'s format.
fn layer_norm_as<B: Backend, const D: usize>(
    ln: &LayerNorm<B>,
    x: Tensor<B, D>,
    out: FloatDType,
    k: &Kernels,
) -> Tensor<B, D> {
    let dims = x.dims();
    let d = dims[D - 1];
    let flat = x.reshape([-1, d as i32]);
    let gamma = ln.gamma.val();
    let beta = match &ln.beta {
        Some(beta) => beta.val(),
        None => Tensor::zeros([d], &gamma.device()),
    };
    let y = match tracked::<B>() {
        Some(op) => op(flat, gamma, beta, out, k),
        None => forward_decomposed(flat, gamma, beta, LN_EPS, (out, None)).y,
    };
    y.reshape(dims)
}

/// The operation on `B`: `[rows, d]`, γ, β in, `[rows, d]` out in the format given.
type NormOp<B> = fn(Tensor<B, 2>, Tensor<B, 1>, Tensor<B, 1>, FloatDType, &Kernels) -> Tensor<B, 2>;

/// The custom operation when `B` is a training backend.
fn tracked<B: Backend>() -> Option<NormOp<B>> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(|| on::<B, burn::backend::Cuda>());
    found
}

/// The operation on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: FusedNorm>() -> Option<NormOp<B>> {
    let plain: NormOp<Autodiff<I>> = apply::<I, NoCheckpointing>;
    let balanced: NormOp<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass of [`layer_norm`].
#[derive(Debug)]
struct Norm;

/// What the backward pass reads: the input, the rows' means and `1/σ`, and γ (inner backend); the kernels.
type Kept<I> = ([FloatTensor<I>; 4], Kernels);

impl<I: FusedNorm> Backward<I, 3> for Norm {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        // A product that read a bf16 output may hand back a bf16 gradient (burn's matmul does).
        let dy = float::<I, 2>(grads.consume::<I>(&ops.node)).cast(FloatDType::F32);
        let ([x, mean, rstd, gamma], k) = ops.state;
        // The input as it was kept (`train.kernels.kept_inputs`): the passes read a bf16 copy as it is.
        let kept = (float(x), float(mean), float(rstd));
        let (dx, dgamma, dbeta) = I::norm_backward(dy, kept, float(gamma), None, &k);
        let [x_node, gamma_node, beta_node] = ops.parents;
        // Only for parents that ask (a frozen norm, an untracked input).
        if let Some(node) = x_node {
            grads.register::<I>(node.id, dx.into_primitive().tensor());
        }
        if let Some(node) = gamma_node {
            grads.register::<I>(node.id, dgamma.into_primitive().tensor());
        }
        if let Some(node) = beta_node {
            grads.register::<I>(node.id, dbeta.into_primitive().tensor());
        }
    }
}

/// [`layer_norm`] of `[rows, d]` as one operation on `Autodiff<I, C>`.
fn apply<I: FusedNorm, C: CheckpointStrategy>(
    x: Tensor<Autodiff<I, C>, 2>,
    gamma: Tensor<Autodiff<I, C>, 1>,
    beta: Tensor<Autodiff<I, C>, 1>,
    out: FloatDType,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 2> {
    let (x, gamma, beta) = (
        x.into_primitive().tensor(),
        gamma.into_primitive().tensor(),
        beta.into_primitive().tensor(),
    );
    let forward = |keep| {
        I::norm_forward(
            float(x.primitive.clone()),
            float(gamma.primitive.clone()),
            float(beta.primitive.clone()),
            LN_EPS,
            (out, keep),
            k,
        )
    };
    let out = match Norm
        .prepare::<C>([x.node.clone(), gamma.node.clone(), beta.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            // An output that feeds products only (`layer_norm_operand`) is rounded to their format: the
            // input kept in that format too costs the backward pass no more than that rounding. The forward
            // kernel writes that copy as it reads the input.
            let keep = k.kept_inputs.format(out);
            let keep = (DType::from(keep) != float::<I, 2>(x.primitive.clone()).dtype()).then_some(keep);
            let normed = forward(keep);
            let kept_x = match normed.kept {
                Some(kept) => kept.into_primitive().tensor(),
                None => x.primitive.clone(),
            };
            let kept = [
                kept_x,
                normed.mean.into_primitive().tensor(),
                normed.rstd.into_primitive().tensor(),
                gamma.primitive.clone(),
            ];
            prep.finish((kept, *k), normed.y.into_primitive().tensor())
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(None).y.into_primitive().tensor()),
    };
    float(out)
}

#[cfg(test)]
mod tests;
