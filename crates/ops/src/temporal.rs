//! Attention over time, as the TAR's temporal layers compute it: every token position of a window attends
//! over its own frames, with queries `[b, t, n, d]` and keys and values `[b, t, n, 2d]` where the layers'
//! products leave them.
//!
//! Grouping the frames of each position as `[b · n, heads, t, dh]` for an attention kernel takes a
//! transposition of the layer's input and output (`[b, t, n, d]` ↔ `[b, n, t, d]`) and of the heads, and
//! burn's attention over 8 keys runs matrix products and a softmax for tiles of 8 × 8: in a profiled
//! `small` step (docs/decisions/007-memory-bound-training-kernels.md) the temporal attention and its transpositions took about 1.8 ms of each
//! TAR layer's forward pass. On the training backends [`over_time_for`] hands out a custom autodiff
//! operation whose passes are [`TemporalAttention`]'s: on CUDA one kernel each (umgen-cuda's `kernels/train/temporal.cu`,
//! one warp per position and head, up to 32 frames) reading the operands in place, so the layer's other
//! operations (norms, products, MLP) work on `[b · t · n, d]` rows with no transposition at all; on the
//! CPU the tiled passes of [`crate::tiled`] after the transpositions that group each position's frames.

#[cfg(feature = "cuda")]
mod cuda;

use crate::dispatch::same;
use crate::format::Precision;
use crate::format::float;
use crate::kernels::Kernels;
use crate::tiled::{tiled_backward, tiled_forward};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;

/// A backend that computes attention over time's two passes. `q` `[b, t, n, d]`, `kv` `[b, t, n, 2d]`
/// (keys, then values), `heads` heads of `d / heads`; `causal` hides later frames. The passes default to
/// burn's operations ([`forward_decomposed`], [`backward_decomposed`]); CUDA overrides them.
pub trait TemporalAttention: Backend {
    /// Whether [`Self::temporal_backward`] reads the forward pass's output and log-sum-exp: the operation
    /// keeps them for the backward pass only then (CUDA's backward kernel recomputes what it needs).
    const KEEPS_FORWARD: bool = true;

    /// The output `[b, t, n, d]` and each query's log-sum-exp of its scaled scores `[b, t, n, heads]`.
    fn temporal_forward(
        q: Tensor<Self, 4>,
        kv: Tensor<Self, 4>,
        heads: usize,
        causal: bool,
        precision: Precision,
        k: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        let _ = k;
        forward_decomposed(q, kv, heads, causal, precision)
    }

    /// The gradients of `q` and `kv` from the output's gradient `dout`, given the forward pass's output and
    /// log-sum-exp when [`Self::KEEPS_FORWARD`] (`saved`; `None` otherwise).
    #[allow(clippy::too_many_arguments)]
    fn temporal_backward(
        q: Tensor<Self, 4>,
        kv: Tensor<Self, 4>,
        saved: Option<Saved<Self>>,
        dout: Tensor<Self, 4>,
        heads: usize,
        causal: bool,
        precision: Precision,
        k: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        let _ = k;
        backward_decomposed(q, kv, saved, dout, heads, causal, precision)
    }
}

/// The forward pass's output and log-sum-exp.
pub type Saved<B> = (Tensor<B, 4>, Tensor<B, 4>);

/// `[b, t, n, heads · dh]` → `[b · n, heads, t, dh]` (a copy).
pub fn to_heads<B: Backend>(x: Tensor<B, 4>, heads: usize) -> Tensor<B, 4> {
    let [b, t, n, d] = x.dims();
    x.reshape([b, t, n, heads, d / heads])
        .permute([0, 2, 3, 1, 4])
        .reshape([b * n, heads, t, d / heads])
}

/// `[b · n, heads, t, dh]` → `[b, t, n, heads · dh]` (a copy).
pub fn from_heads<B: Backend>(x: Tensor<B, 4>, b: usize, n: usize) -> Tensor<B, 4> {
    let [_, heads, t, dh] = x.dims();
    x.reshape([b, n, heads, t, dh])
        .permute([0, 3, 1, 2, 4])
        .reshape([b, t, n, heads * dh])
}

/// Keys and values of `kv` `[b, t, n, 2d]`.
fn split<B: Backend>(kv: Tensor<B, 4>) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let d = kv.dims()[3] / 2;
    (kv.clone().narrow(3, 0, d), kv.narrow(3, d, d))
}

/// [`TemporalAttention::temporal_forward`] through the transpositions and the tiled forward pass.
pub fn forward_decomposed<B: Backend>(
    q: Tensor<B, 4>,
    kv: Tensor<B, 4>,
    heads: usize,
    causal: bool,
    precision: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let [b, t, n, _] = q.dims();
    let (k, v) = split(kv);
    let h = |x| to_heads(x, heads);
    let (out, lse) = tiled_forward(h(q), h(k), h(v), causal, t, precision.attention());
    // [b · n, heads, t, 1] → [b, t, n, heads]
    let lse = lse.reshape([b, n, heads, t]).permute([0, 3, 1, 2]);
    (from_heads(out, b, n), lse)
}

/// [`TemporalAttention::temporal_backward`] through the transpositions and the tiled backward pass; the
/// forward pass is recomputed when `saved` is `None`.
pub fn backward_decomposed<B: Backend>(
    q: Tensor<B, 4>,
    kv: Tensor<B, 4>,
    saved: Option<Saved<B>>,
    dout: Tensor<B, 4>,
    heads: usize,
    causal: bool,
    precision: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let (out, lse) =
        saved.unwrap_or_else(|| forward_decomposed(q.clone(), kv.clone(), heads, causal, precision));
    let [b, t, n, _] = q.dims();
    let (k, v) = split(kv);
    let h = |x| to_heads(x, heads);
    let lse = lse.permute([0, 2, 3, 1]).reshape([b * n, heads, t, 1]);
    let (dq, dk, dv) = tiled_backward(
        h(q),
        h(k),
        h(v),
        h(out),
        lse,
        h(dout),
        causal,
        t,
        precision.attention(),
    );
    let dkv = Tensor::cat(vec![from_heads(dk, b, n), from_heads(dv, b, n)], 3);
    (from_heads(dq, b, n), dkv)
}

/// The CPU computes the decomposition.
impl TemporalAttention for burn::backend::Flex {}

/// Attention over time on `B`: `q` `[b, t, n, d]`, `kv` `[b, t, n, 2d]`, heads, causal, the products'
/// precision, the kernels; the output `[b, t, n, d]`.
pub type OverTime<B> = fn(Tensor<B, 4>, Tensor<B, 4>, usize, bool, Precision, &Kernels) -> Tensor<B, 4>;

/// The operation when `B` is a training backend; `None` elsewhere (inference backends keep the layer's
/// transposed path).
pub fn over_time_for<B: Backend>() -> Option<OverTime<B>> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// The operation on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: TemporalAttention>() -> Option<OverTime<B>> {
    let plain: OverTime<Autodiff<I>> = apply::<I, NoCheckpointing>;
    let balanced: OverTime<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass.
#[derive(Debug)]
struct Temporal;

/// q, kv, and the output and log-sum-exp where the backend's backward pass reads them (inner backend);
/// heads, causal, precision, the kernels.
type Kept<I> = (
    [FloatTensor<I>; 2],
    Option<[FloatTensor<I>; 2]>,
    usize,
    bool,
    Precision,
    Kernels,
);

impl<I: TemporalAttention> Backward<I, 2> for Temporal {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dout = float::<I, 4>(grads.consume::<I>(&ops.node));
        let ([q, kv], saved, heads, causal, precision, k) = ops.state;
        let saved = saved.map(|[out, lse]| (float(out), float(lse)));
        let (dq, dkv) = I::temporal_backward(float(q), float(kv), saved, dout, heads, causal, precision, &k);
        let [q_node, kv_node] = ops.parents;
        if let Some(node) = q_node {
            grads.register::<I>(node.id, dq.into_primitive().tensor());
        }
        if let Some(node) = kv_node {
            grads.register::<I>(node.id, dkv.into_primitive().tensor());
        }
    }
}

/// Attention over time as one operation on `Autodiff<I, C>`.
fn apply<I: TemporalAttention, C: CheckpointStrategy>(
    q: Tensor<Autodiff<I, C>, 4>,
    kv: Tensor<Autodiff<I, C>, 4>,
    heads: usize,
    causal: bool,
    precision: Precision,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 4> {
    let (q, kv) = (q.into_primitive().tensor(), kv.into_primitive().tensor());
    let (out, lse) = I::temporal_forward(
        float(q.primitive.clone()),
        float(kv.primitive.clone()),
        heads,
        causal,
        precision,
        k,
    );
    let out = out.into_primitive().tensor();
    let result = match Temporal
        .prepare::<C>([q.node.clone(), kv.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let inputs = [q.primitive.clone(), kv.primitive.clone()];
            let saved = I::KEEPS_FORWARD.then(|| [out.clone(), lse.into_primitive().tensor()]);
            prep.finish((inputs, saved, heads, causal, precision, *k), out)
        }
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    float(result)
}

#[cfg(test)]
mod tests;
