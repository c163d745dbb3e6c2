//! The training attention as a custom autodiff operation that keeps only its inputs, output and each row's
//! log-sum-exp ([`tiled_autodiff`]), its passes the backend's [`FusedAttention`] (fused kernels on CUDA,
//! [`crate::tiled`]'s blocks elsewhere).
//!
//! burn 0.21's autodiff differentiates attention through its decomposed fallback, which keeps the whole
//! `[b, h, lq, lk]` probability matrix (and the scores) alive until the backward pass: with a frame of
//! N ≈ 2,200 tokens that is most of the memory of a training step.
//!
//! Dispatch: the model is generic over `B: Backend`, and Rust has no specialisation, so [`attend`] recognises
//! the autodiff backends this workspace trains on by their type id and routes them here; any other backend
//! takes burn's `attention` (fused on CUDA for inference, the decomposed path elsewhere), which computes the
//! same function.

use crate::dispatch::same;
use crate::flash::FusedAttention;
use crate::format::{Precision, float};
use crate::heads::split_kv;
use crate::kernels::Kernels;
use crate::tiled::{MIN_TILED_KEYS, operands};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::backend::Backend;
use burn::tensor::module::attention;
use burn::tensor::ops::{AttentionModuleOptions, FloatTensor};
use burn::tensor::{Bool, Tensor};

mod kv;
mod masked;

/// `softmax(q kᵀ / √d) v` over `[b, h, l, d]` tensors; `causal` hides keys after each query (bottom-right
/// aligned, as burn's `is_causal`). Without a mask, training backends take the tiled operation, whose
/// products follow `precision.attention()`; the decomposed path stays f32.
pub fn attend<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    mask: Option<Tensor<B, 4, Bool>>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> Tensor<B, 4> {
    let precision = precision.attention();
    let [_, _, lq, _] = q.dims();
    let lk = k.dims()[2];
    match tiled_for::<B>() {
        Some(tiled) if mask.is_none() && lk >= MIN_TILED_KEYS && (!causal || lk >= lq) => {
            tiled(q, k, v, causal, precision, kernels)
        }
        // The training backends differentiate burn's decomposition; the shift by each row's maximum
        // needs no gradient (`attention/masked.rs`).
        Some(_) => masked::attention_shift_detached(q, k, v, mask, causal),
        None => {
            let opts = AttentionModuleOptions {
                is_causal: causal,
                ..Default::default()
            };
            attention(q, k, v, mask, None, opts)
        }
    }
}

/// [`attend`] with keys and values as one tensor `kv` `[b, lk, 2d]` (keys' columns, then values'), split
/// into `heads` heads: on the training backends (no mask, long key sequences) one operation whose
/// backward pass returns `kv`'s gradient as one tensor (`attention/kv.rs`).
pub fn attend_kv<B: Backend>(
    q: Tensor<B, 4>,
    kv: Tensor<B, 3>,
    mask: Option<Tensor<B, 4, Bool>>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> Tensor<B, 4> {
    let [_, heads, lq, _] = q.dims();
    let lk = kv.dims()[1];
    match kv::kv_for::<B>() {
        Some(f) if one_operation(mask.is_none(), lq, lk, causal) => {
            f(q, kv, causal, precision.attention(), kernels)
        }
        _ => {
            let (k, v) = split_kv(kv, heads);
            attend(q, k, v, mask, causal, precision, kernels)
        }
    }
}

/// Whether [`attend_kv`] runs `lq` queries over `lk` keys as one operation on the training backend `B`
/// (whose operands it casts to the attention's format itself, so that they may come in that format).
pub fn attends_kv_in_one<B: Backend>(unmasked: bool, lq: usize, lk: usize, causal: bool) -> bool {
    kv::kv_for::<B>().is_some() && one_operation(unmasked, lq, lk, causal)
}

/// The shapes [`attend_kv`]'s one operation takes: no mask, long key sequences, and under a causal mask
/// at least as many keys as queries.
fn one_operation(unmasked: bool, lq: usize, lk: usize, causal: bool) -> bool {
    unmasked && lk >= MIN_TILED_KEYS && (!causal || lk >= lq)
}

/// The signature of an attention function on backend `B`.
type AttentionFn<B> = fn(Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>, bool, Precision, &Kernels) -> Tensor<B, 4>;

/// The tiled operation as a function on `B`, when `B` is one of the autodiff backends named here; `None`
/// otherwise (inference backends, or a backend this list does not know).
pub fn tiled_for<B: Backend>() -> Option<AttentionFn<B>> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// `tiled_autodiff` on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: FusedAttention>() -> Option<AttentionFn<B>> {
    let plain: AttentionFn<Autodiff<I, NoCheckpointing>> = tiled_autodiff::<I, NoCheckpointing>;
    let balanced: AttentionFn<Autodiff<I, BalancedCheckpointing>> =
        tiled_autodiff::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

#[derive(Debug)]
struct TiledAttention;

impl<B: FusedAttention> Backward<B, 3> for TiledAttention {
    /// q, k, v, output, log-sum-exp, causal, precision of the products, the kernels.
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        bool,
        Precision,
        Kernels,
    );

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [nq, nk, nv] = ops.parents;
        let dout = float::<B, 4>(grads.consume::<B>(&ops.node));
        let (q, k, v, out, lse, causal, precision, kernels) = ops.state;
        let (q, k, v, out, lse) = (float(q), float(k), float(v), float(out), float(lse));
        let (dq, dk, dv) = B::attention_backward(q, k, v, out, lse, dout, causal, precision, &kernels);
        for (node, g) in [(nq, dq), (nk, dk), (nv, dv)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g.into_primitive().tensor());
            }
        }
    }
}

/// The training attention on `Autodiff<I, C>`: forward through `I`'s [`FusedAttention::attention_forward`]
/// (fused kernels on CUDA, [`crate::tiled::tiled_forward`] elsewhere), keeping its inputs, output and log-sum-exp for
/// [`FusedAttention::attention_backward`].
pub fn tiled_autodiff<I: FusedAttention, C: CheckpointStrategy>(
    q: Tensor<Autodiff<I, C>, 4>,
    k: Tensor<Autodiff<I, C>, 4>,
    v: Tensor<Autodiff<I, C>, 4>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> Tensor<Autodiff<I, C>, 4> {
    let (q, k, v) = (
        q.into_primitive().tensor(),
        k.into_primitive().tensor(),
        v.into_primitive().tensor(),
    );
    let prep = TiledAttention
        .prepare::<C>([q.node.clone(), k.node.clone(), v.node.clone()])
        .compute_bound()
        .stateful();
    // Cast here, so that the backward pass keeps the inputs in the products' format (half the memory in
    // bf16) and neither pass casts them again.
    let (qi, ki, vi) = operands(
        float::<I, 4>(q.primitive),
        float::<I, 4>(k.primitive),
        float::<I, 4>(v.primitive),
        precision,
    );
    let (out, lse) = I::attention_forward(qi.clone(), ki.clone(), vi.clone(), causal, precision, kernels);
    let out_p = out.clone().into_primitive().tensor();
    let y = match prep {
        OpsKind::Tracked(prep) => {
            let state = (
                qi.into_primitive().tensor(),
                ki.into_primitive().tensor(),
                vi.into_primitive().tensor(),
                out.into_primitive().tensor(),
                lse.into_primitive().tensor(),
                causal,
                precision,
                *kernels,
            );
            prep.finish(state, out_p)
        }
        OpsKind::UnTracked(prep) => prep.finish(out_p),
    };
    float(y)
}
