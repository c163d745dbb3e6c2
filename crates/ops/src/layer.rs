//! A pre-norm attention layer as one autodiff operation whose backward pass is written out by hand
//! (`layer/math.rs`), in one of two modes.
//!
//! - **Recomputed** (`train.kernels.recompute`, activation checkpointing): a training step keeps about
//!   twenty activations of a layer's width for each layer's backward pass; `paper` (72 self-attention
//!   layers over 20 × 2,199 tokens of width 768) needs more than an H200 holds. Each self-attention layer
//!   ([`LayerParts`]: the OAR layers and both halves of every TAR block) keeps only its input (and
//!   dropout masks, when dropout is on) and recomputes its activations in the backward pass, as PyTorch's
//!   `torch.utils.checkpoint` does for the reference. The cost is one more forward pass of those layers
//!   per step. The cross-attention layers without a mask (the ego module's layers over each frame's
//!   environment, [`cross_op_for`]) do the same: each keeps its queries' input and the context every
//!   layer of the stack shares, where it would keep its own normalised context and keys and values (about
//!   0.2 GiB a layer of `paper`).
//! - **Kept** (`train.kernels.layer = "fused"` without recomputation): the operation keeps the
//!   activations its backward pass reads, about what burn's autodiff of the layer's operations keeps,
//!   and its backward pass reads them. Against burn's autodiff it sums the gradients that meet on one
//!   tensor inside the kernels that write them and puts one node in the autodiff graph per layer instead
//!   of about fifteen.
//!
//! burn 0.21 cannot run autodiff inside a backward step (`math.rs` says why), hence the hand-written
//! backward pass. Like the other training operations the operation exists for the autodiff backends this
//! workspace trains on (CUDA, and the CPU's `Flex`, where the tests compare it with burn's autodiff);
//! elsewhere, and with `layer = "burn"` and recomputation off (the defaults), layers take burn's autodiff.

mod math;
mod params;

use crate::dispatch::same;
use crate::format::Precision;
use crate::format::float;
use crate::kernels::{Kernels, LayerKernel};
use burn::backend::Autodiff;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Distribution, Tensor};
use math::{Keep, LayerBackend, Mask, Masks, Setting, Weights};
use params::weights;
use std::sync::atomic::{AtomicU64, Ordering};

/// Layer passes with a backward pass to come run by the operation so far, recomputed and kept (the bench
/// prints them, tests check the path was taken); a pass that wants no gradients keeps nothing and counts in
/// neither.
static RECOMPUTED: AtomicU64 = AtomicU64::new(0);
static KEPT: AtomicU64 = AtomicU64::new(0);

/// How many layer passes the operation has run in this process recomputing their activations.
pub fn layers_recomputed() -> u64 {
    RECOMPUTED.load(Ordering::Relaxed)
}

/// How many layer passes the operation has run in this process keeping their activations.
pub fn layers_kept() -> u64 {
    KEPT.load(Ordering::Relaxed)
}

/// The parts of a pre-norm self-attention layer (`x + proj(attn(ln1(x)))`, then `x + out(gelu(fc(ln2(x))))`),
/// borrowed from the model that holds them.
#[derive(Debug)]
pub struct LayerParts<'a, B: Backend> {
    /// The attention's layer norm (of the queries, in a cross-attention layer).
    pub ln1: &'a LayerNorm<B>,
    /// A cross-attention layer's norm of its context; `None` in a self-attention layer.
    pub ln_ctx: Option<&'a LayerNorm<B>>,
    /// The queries' projection.
    pub q: &'a Linear<B>,
    /// The keys' and values' projection, keys' columns first.
    pub kv: &'a Linear<B>,
    /// The attention's output projection.
    pub proj: &'a Linear<B>,
    /// The MLP's layer norm.
    pub ln2: &'a LayerNorm<B>,
    /// The MLP's first layer (followed by GELU).
    pub fc: &'a Linear<B>,
    /// The MLP's second layer.
    pub out: &'a Linear<B>,
    /// Attention heads.
    pub heads: usize,
    /// The products' format.
    pub precision: Precision,
    /// Dropout on the attention's output.
    pub attn_dropout: f64,
    /// Dropout on the MLP's output.
    pub mlp_dropout: f64,
}

/// A self-attention layer applied to `x` `[b, l, d]` (`causal` or not); with `Some((t, n))` a TAR temporal
/// layer on `l = t · n` rows, each position attending over its own `t` frames (`math::Setting::over_time`).
/// `Err(x)` hands the input back for a layer the operation does not take (one without biases), which the
/// caller runs through burn's autodiff.
pub type LayerFn<B> =
    fn(&LayerParts<'_, B>, Tensor<B, 3>, bool, Option<(usize, usize)>, &Kernels) -> Taken<B>;

/// The layer's output, or its input handed back (`Err`) for a layer the operation does not take.
pub type Taken<B> = Result<Tensor<B, 3>, Tensor<B, 3>>;

/// A cross-attention layer without a mask applied to queries `x` `[b, lq, d]` over `ctx` `[b, lk, d]`
/// (`parts.ln_ctx` set); `Err((x, ctx))` hands both back for a layer the operation does not take.
pub type CrossFn<B> = fn(&LayerParts<'_, B>, Tensor<B, 3>, Tensor<B, 3>, &Kernels) -> CrossTaken<B>;

/// The layer's output, or its inputs handed back (`Err`).
pub type CrossTaken<B> = Result<Tensor<B, 3>, (Tensor<B, 3>, Tensor<B, 3>)>;

/// Whether `k` asks for the operation: recomputation, or `layer = "fused"`.
fn asked(k: &Kernels) -> bool {
    k.recompute || k.layer == LayerKernel::Fused
}

/// The layer as one operation on `B`, when `k` asks for it ([`asked`]) and `B` is an autodiff backend
/// this workspace trains on; `None` otherwise.
pub fn layer_op_for<B: Backend>(k: &Kernels) -> Option<LayerFn<B>> {
    if !asked(k) {
        return None;
    }
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// The cross-attention layer as one operation on `B`, under the same conditions as [`layer_op_for`].
pub fn cross_op_for<B: Backend>(k: &Kernels) -> Option<CrossFn<B>> {
    if !asked(k) {
        return None;
    }
    let found = on_cross::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on_cross::<B, burn::backend::Cuda>);
    found
}

/// [`self_layer`] on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: LayerBackend>() -> Option<LayerFn<B>> {
    let plain: LayerFn<Autodiff<I, NoCheckpointing>> = self_layer::<I, NoCheckpointing>;
    let balanced: LayerFn<Autodiff<I, BalancedCheckpointing>> = self_layer::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// [`cross_layer`] on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on_cross<B: Backend, I: LayerBackend>() -> Option<CrossFn<B>> {
    let plain: CrossFn<Autodiff<I, NoCheckpointing>> = cross_layer::<I, NoCheckpointing>;
    let balanced: CrossFn<Autodiff<I, BalancedCheckpointing>> = cross_layer::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// Parents of the operation: the input, then the parameters in [`Weights`]' order.
const PARENTS: usize = 15;

/// Parents of the cross-attention operation: the queries' input, the context, then the parameters in
/// [`Weights`]' order (the context's norm among them).
const CROSS_PARENTS: usize = 18;

#[derive(Debug)]
struct LayerOp;

/// What the operation keeps for its backward pass: the input (in the format
/// `train.kernels.kept_inputs` names) or every activation the backward pass reads, the parameters
/// (handles to the tensors the model holds anyway), the settings and the dropout masks.
#[derive(Debug, Clone)]
struct Kept<I: LayerBackend> {
    kept: math::Kept<I>,
    weights: Weights<I>,
    setting: Setting,
    masks: Masks<I>,
}

impl<I: LayerBackend> Kept<I> {
    /// The gradients of the input, of the context `ctx` (if any) and of the parameters in [`Weights`]'
    /// order, from the output's gradient `dy`.
    fn gradients(
        self,
        ctx: Option<Tensor<I, 3>>,
        dy: Tensor<I, 3>,
    ) -> (Tensor<I, 3>, Option<Tensor<I, 3>>, math::WeightGrads<I>) {
        let (w, s, m) = (&self.weights, self.setting, &self.masks);
        match self.kept {
            // The input as it was kept (`train.kernels.kept_inputs`): the norms' kernels read a bf16 copy
            // as it is, and the residual add widens it inside its fused kernel.
            math::Kept::Input(x) => math::backward(w, s, m, (x, ctx), dy),
            // The activations hold the context's own (a cross-attention layer's `ctx` is that tensor).
            math::Kept::Activations(f) => math::gradients(w, s, m, *f, dy),
        }
    }
}

/// Registers each gradient for its parent, skipping parents that need none.
fn register<I: LayerBackend>(
    grads: &mut Gradients,
    parents: impl IntoIterator<Item = Option<NodeId>>,
    values: impl IntoIterator<Item = FloatTensor<I>>,
) {
    for (node, g) in parents.into_iter().zip(values) {
        if let Some(id) = node {
            grads.register::<I>(id, g);
        }
    }
}

impl<I: LayerBackend> Backward<I, PARENTS> for LayerOp {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, PARENTS>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = float::<I, 3>(grads.consume::<I>(&ops.node));
        let (dx, _, dw) = ops.state.gradients(None, dy);
        let values = std::iter::once(dx.into_primitive().tensor()).chain(dw.into_iter().map(|g| g.tensor()));
        register::<I>(
            grads,
            ops.parents.iter().map(|n| n.as_ref().map(|n| n.id)),
            values,
        );
    }
}

#[derive(Debug)]
struct CrossOp;

impl<I: LayerBackend> Backward<I, CROSS_PARENTS> for CrossOp {
    /// What [`LayerOp`] keeps, and the context as the caller holds it (one tensor for every layer of
    /// a stack, so not cast).
    type State = (Kept<I>, Tensor<I, 3>);

    fn backward(self, ops: Ops<Self::State, CROSS_PARENTS>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = float::<I, 3>(grads.consume::<I>(&ops.node));
        let (kept, ctx) = ops.state;
        let (dx, dctx, dw) = kept.gradients(Some(ctx), dy);
        let values = [Some(dx), dctx]
            .into_iter()
            .flatten()
            .map(|t| t.into_primitive().tensor())
            .chain(dw.into_iter().map(|g| g.tensor()));
        register::<I>(
            grads,
            ops.parents.iter().map(|n| n.as_ref().map(|n| n.id)),
            values,
        );
    }
}

/// The layer on `Autodiff<I, C>` as one operation; `Err(x)` for a layer without biases (every layer the
/// backbone builds has them) or with a context's norm.
fn self_layer<I: LayerBackend, C: CheckpointStrategy>(
    parts: &LayerParts<'_, Autodiff<I, C>>,
    x: Tensor<Autodiff<I, C>, 3>,
    causal: bool,
    over_time: Option<(usize, usize)>,
    kernels: &Kernels,
) -> Taken<Autodiff<I, C>> {
    let Some((weights, tracked)) = weights(parts).filter(|_| parts.ln_ctx.is_none()) else {
        return Err(x);
    };
    let x = x.into_primitive().tensor();
    let parents = std::array::from_fn(|i| match i {
        0 => x.node.clone(),
        i => tracked[i - 1].node.clone(),
    });
    let run = |backward| {
        let shape = (causal, over_time);
        start(parts, weights, float(x.primitive), None, shape, kernels, backward)
    };
    let out = match LayerOp.prepare::<C>(parents).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let (kept, y) = run(true);
            prep.finish(kept, y)
        }
        OpsKind::UnTracked(prep) => prep.finish(run(false).1),
    };
    Ok(float(out))
}

/// The cross-attention layer on `Autodiff<I, C>` as one operation; `Err((x, ctx))` for a layer without
/// biases or without a context's norm.
fn cross_layer<I: LayerBackend, C: CheckpointStrategy>(
    parts: &LayerParts<'_, Autodiff<I, C>>,
    x: Tensor<Autodiff<I, C>, 3>,
    ctx: Tensor<Autodiff<I, C>, 3>,
    kernels: &Kernels,
) -> CrossTaken<Autodiff<I, C>> {
    let Some((weights, tracked)) = weights(parts).filter(|_| parts.ln_ctx.is_some()) else {
        return Err((x, ctx));
    };
    let (x, ctx) = (x.into_primitive().tensor(), ctx.into_primitive().tensor());
    let parents = std::array::from_fn(|i| match i {
        0 => x.node.clone(),
        1 => ctx.node.clone(),
        i => tracked[i - 2].node.clone(),
    });
    let ci = float::<I, 3>(ctx.primitive);
    let run = |backward| {
        let c = Some(ci.clone());
        start(
            parts,
            weights,
            float(x.primitive),
            c,
            (false, None),
            kernels,
            backward,
        )
    };
    let out = match CrossOp.prepare::<C>(parents).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let (kept, y) = run(true);
            prep.finish((kept, ci), y)
        }
        OpsKind::UnTracked(prep) => prep.finish(run(false).1),
    };
    Ok(float(out))
}

/// Both operations' forward pass on the inner backend, for input `x` (and a cross-attention layer's
/// context `ctx`) with (`causal`, `over_time`): what the backward pass keeps (nothing it needs without
/// a `backward` pass to come), and the output.
fn start<I: LayerBackend, C: CheckpointStrategy>(
    parts: &LayerParts<'_, Autodiff<I, C>>,
    weights: Weights<I>,
    x: Tensor<I, 3>,
    ctx: Option<Tensor<I, 3>>,
    (causal, over_time): (bool, Option<(usize, usize)>),
    kernels: &Kernels,
    backward: bool,
) -> (Kept<I>, FloatTensor<I>) {
    let setting = Setting {
        heads: parts.heads,
        causal,
        precision: parts.precision,
        eps: crate::norm::LN_EPS,
        over_time,
        kernels: *kernels,
    };
    let all = !kernels.recompute;
    if backward {
        let counter = if all { &KEPT } else { &RECOMPUTED };
        counter.fetch_add(1, Ordering::Relaxed);
    }
    let masks = Masks {
        attn: draw_mask(&x, parts.attn_dropout),
        mlp: draw_mask(&x, parts.mlp_dropout),
    };
    let format = kernels.kept_inputs.format(parts.precision.operand_dtype());
    let keep = Keep {
        format: (backward && DType::from(format) != x.dtype()).then_some(format),
        all: all && backward,
    };
    let (y, kept) = math::forward(&weights, setting, &masks, x, ctx, keep);
    let y = y.into_primitive().tensor();
    let kept = Kept {
        kept,
        weights,
        setting,
        masks,
    };
    (kept, y)
}

/// A dropout keep-mask for an output shaped like `x`, drawn as burn's `Dropout` draws it on an autodiff
/// backend; none when `prob` is 0.
fn draw_mask<I: LayerBackend>(x: &Tensor<I, 3>, prob: f64) -> Mask<I> {
    let keep = 1.0 - prob;
    (prob > 0.0).then(|| {
        (
            x.random_like(Distribution::Bernoulli(keep)).greater_elem(0.5),
            1.0 / keep,
        )
    })
}

#[cfg(test)]
mod tests;
