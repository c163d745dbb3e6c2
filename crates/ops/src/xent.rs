//! Cross-entropy from logits as one autodiff operation on the training backends.
//!
//! burn's `log_softmax` followed by `gather` keeps the log-probabilities for the backward pass, runs
//! log-softmax's own backward (a sum over the vocabulary) after scattering the gathered gradient into a
//! zero `[rows, vocab]` tensor, and so passes over every logit several times; the map and image heads of
//! `small` produce 1.6 GB of f32 logits per head set. [`sum`] computes the loss from the logits and each
//! row's log-sum-exp and, in the backward pass, the gradient in one expression: `g · (softmax − q)`, with
//! q the target distribution of [`crate::smoothing::Targets`] scattered in. Elsewhere (inference backends)
//! it is `log_softmax` and [`crate::smoothing::nll_sum`]. The two passes over the logits are
//! [`FusedXent`]'s: on CUDA one kernel each (umgen-cuda's `kernels/train/xent.cu`, a warp a row: an online log-sum-exp forward,
//! one read and one write backward) unless `train.kernels.xent = "burn"`; on the CPU burn's operations
//! ([`lse_decomposed`], [`grad_decomposed`]).

#[cfg(feature = "cuda")]
mod cuda;

use crate::dispatch::{Fallbacks, same};
use crate::format::float;
use crate::kernels::Kernels;
pub use crate::kernels::XentKernel;
use crate::smoothing::{Targets, nll_sum};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::activation::log_softmax;
use burn::tensor::backend::Backend;
use burn::tensor::{IndexingUpdateOp, Int, Tensor};

/// Passes the kernels refused in this process.
static FALLBACKS: Fallbacks = Fallbacks::new("cross-entropy");

/// How many cross-entropy passes fell back from the CUDA kernels to burn's operations in this process.
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}

/// A backend that computes the two passes of a cross-entropy over the rows of `[rows, vocab]` logits. The
/// passes default to burn's operations ([`lse_decomposed`], [`grad_decomposed`]); CUDA overrides them.
pub trait FusedXent: Backend {
    /// Each row's `log Σ exp x` `[rows, 1]`.
    fn xent_lse(x: Tensor<Self, 2>, k: &Kernels) -> Tensor<Self, 2> {
        let _ = k;
        lse_decomposed(x)
    }

    /// The logits' gradient `g · (exp(x − lse) − q)` of the summed loss, with `g` `[1]` the loss's
    /// gradient and q the target weights `weights` `[rows, k]` at `ids` `[rows, k]` (repeated ids add up).
    fn xent_grad(
        x: Tensor<Self, 2>,
        lse: Tensor<Self, 2>,
        ids: Tensor<Self, 2, Int>,
        weights: Tensor<Self, 2>,
        g: Tensor<Self, 1>,
        k: &Kernels,
    ) -> Tensor<Self, 2> {
        let _ = k;
        grad_decomposed(x, lse, ids, weights, g)
    }
}

/// [`FusedXent::xent_lse`] as burn operations.
pub fn lse_decomposed<B: Backend>(x: Tensor<B, 2>) -> Tensor<B, 2> {
    let m = x.clone().max_dim(1);
    (x - m.clone()).exp().sum_dim(1).log() + m
}

/// [`FusedXent::xent_grad`] as burn operations.
pub fn grad_decomposed<B: Backend>(
    x: Tensor<B, 2>,
    lse: Tensor<B, 2>,
    ids: Tensor<B, 2, Int>,
    weights: Tensor<B, 2>,
    g: Tensor<B, 1>,
) -> Tensor<B, 2> {
    (x - lse)
        .exp()
        .scatter(1, ids, weights.neg(), IndexingUpdateOp::Add)
        * g.unsqueeze::<2>()
}

impl FusedXent for burn::backend::Flex {}

/// The summed loss of logits `[rows, vocab]` against `targets` `[rows, 1]`, as
/// [`crate::smoothing::nll_sum`] of their log-softmax defines it.
pub fn sum<B: Backend>(
    logits: Tensor<B, 2>,
    targets: Tensor<B, 2, Int>,
    ordinal: usize,
    sigma: f64,
    k: &Kernels,
) -> Tensor<B, 1> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    match found {
        Some(op) => op(logits, targets, ordinal, sigma, k),
        None => nll_sum(log_softmax(logits, 1), targets, ordinal, sigma),
    }
}

/// The loss on `B`.
type LossFn<B> = fn(Tensor<B, 2>, Tensor<B, 2, Int>, usize, f64, &Kernels) -> Tensor<B, 1>;

/// [`apply`] on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: FusedXent>() -> Option<LossFn<B>> {
    let plain: LossFn<Autodiff<I>> = apply::<I, NoCheckpointing>;
    let balanced: LossFn<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

#[derive(Debug)]
struct Xent;

/// The logits, their log-sum-exp, the target distribution and the kernels.
type Kept<I> = (Tensor<I, 2>, Tensor<I, 2>, Targets<I>, Kernels);

impl<I: FusedXent> Backward<I, 1> for Xent {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let g = float::<I, 1>(grads.consume::<I>(&ops.node));
        let [node] = ops.parents;
        let Some(node) = node else { return };
        let (x, lse, q, k) = ops.state;
        let dx = I::xent_grad(x, lse, q.ids, q.weights, g, &k);
        grads.register::<I>(node.id, dx.into_primitive().tensor());
    }
}

/// [`sum`] as one operation on `Autodiff<I, C>`.
fn apply<I: FusedXent, C: CheckpointStrategy>(
    logits: Tensor<Autodiff<I, C>, 2>,
    targets: Tensor<Autodiff<I, C>, 2, Int>,
    ordinal: usize,
    sigma: f64,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 1> {
    let t = logits.into_primitive().tensor();
    let x = float::<I, 2>(t.primitive.clone());
    let targets = Tensor::<I, 2, Int>::from_primitive(targets.into_primitive());
    let q = Targets::new(targets, ordinal, sigma, x.dims()[1]);
    let lse = I::xent_lse(x.clone(), k);
    // −Σ q log p = Σ_rows (lse − Σ_k q_k x_k), as the weights of a row sum to 1.
    let cross = lse.clone().sum() - (x.clone().gather(1, q.ids.clone()) * q.weights.clone()).sum();
    let loss = (q.entropy() + cross).into_primitive().tensor();
    let out = match Xent.prepare::<C>([t.node.clone()]).compute_bound().stateful() {
        OpsKind::Tracked(prep) => prep.finish((x, lse, q, *k), loss),
        OpsKind::UnTracked(prep) => prep.finish(loss),
    };
    float(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::Flex;
    use burn::tensor::{Distribution, TensorData};

    type A = Autodiff<Flex>;

    /// Loss and logit gradient equal to `log_softmax` + `nll_sum` under burn's autodiff, hard and
    /// smoothed, with category targets (ids ≥ ordinal) among ordered ones and a window cut at the ends.
    #[test]
    fn matches_log_softmax_and_gather() {
        let dev = Default::default();
        let x = Tensor::<A, 2>::random([7, 20], Distribution::Normal(0.0, 3.0), &dev).require_grad();
        let t: Vec<i64> = vec![0, 3, 15, 16, 19, 9, 1];
        let t = Tensor::<A, 2, Int>::from_data(TensorData::new(t, [7, 1]), &dev);
        for sigma in [0.0, 1.5] {
            let ours = sum(x.clone(), t.clone(), 16, sigma, &Kernels::default());
            let theirs = nll_sum(log_softmax(x.clone(), 1), t.clone(), 16, sigma);
            let (a, b) = (ours.clone().into_scalar(), theirs.clone().into_scalar());
            assert!((a - b).abs() < 1e-4 * b.abs().max(1.0), "σ {sigma}: {a} vs {b}");
            let (ga, gb) = (ours.backward(), theirs.backward());
            let (ga, gb) = (x.grad(&ga).expect("grad"), x.grad(&gb).expect("grad"));
            let err = (ga - gb).abs().max().into_scalar();
            assert!(err < 1e-5, "σ {sigma}: gradient differs by {err}");
        }
    }

    #[test]
    fn training_backends_take_the_operation() {
        assert!(on::<A, Flex>().is_some());
        assert!(on::<Flex, Flex>().is_none());
    }
}
