//! Tiled (memory-efficient) attention for training: FlashAttention's algorithm written with backend tensor
//! operations, as a custom autodiff operation.
//!
//! burn 0.21's autodiff differentiates attention through its decomposed fallback, which keeps the whole
//! `[b, h, lq, lk]` probability matrix (and the scores) alive until the backward pass: with a frame of
//! N ≈ 2,200 tokens that is most of the memory of a training step. Here the forward pass walks blocks of
//! queries, keeps only the output and each row's log-sum-exp, and the backward pass recomputes every block's
//! probabilities from them (FlashAttention-2, Dao 2023, algorithm 2). Causal blocks stop at their last visible
//! key, which also halves the matrix work. Memory is O(b·h·block·lk) instead of O(b·h·lq·lk).
//!
//! Dispatch: the model is generic over `B: Backend`, and Rust has no specialisation, so [`attend`] recognises
//! the autodiff backends this workspace trains on by their type id and routes them here; any other backend
//! takes burn's `attention` (fused on CUDA for inference, the decomposed path elsewhere), which computes the
//! same function.

use crate::config::Precision;
use crate::dispatch::same;
use crate::flash::FusedAttention;
use crate::precision::{matmul, operand};
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
use burn::tensor::{Bool, FloatDType, Tensor, TensorPrimitive};
use std::sync::atomic::{AtomicUsize, Ordering};

mod kv;
mod masked;
pub(crate) use kv::split_kv;

/// Shorter key sequences take the decomposed path: their score matrices are no larger than a few copies of
/// the keys, and the block loop only adds launches (H200, `umgen-kernel-bench attention`: 70,352 sequences of 8
/// tokens took 15.8 ms tiled against 8.1 ms decomposed; 32 × 6 heads × 2,199 causal tokens 34 ms against
/// 101 ms, in 3.4 GiB instead of 29.6).
pub(crate) const MIN_TILED_KEYS: usize = 256;

/// Bytes one block's score matrix may take by default; sets the query block length. Few, large blocks:
/// every causal block has its own key length, hence its own kernel shapes to compile and tune on CUDA.
pub const BLOCK_BYTES: usize = 1 << 30;

/// [`set_block_bytes`]'s value; 0 for [`BLOCK_BYTES`].
static BLOCK_BYTES_SET: AtomicUsize = AtomicUsize::new(0);

/// Sets the bytes one query block's scores may take in training, process-wide (`None`: the default,
/// 1 GiB). Smaller blocks skip more of a causal matrix's hidden half and launch more, smaller kernels;
/// `umgen-kernel-bench attention --block-mib` compares sizes.
pub fn set_block_bytes(bytes: Option<usize>) {
    BLOCK_BYTES_SET.store(bytes.unwrap_or(0), Ordering::Relaxed);
}

fn block_bytes() -> usize {
    match BLOCK_BYTES_SET.load(Ordering::Relaxed) {
        0 => BLOCK_BYTES,
        b => b,
    }
}

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
) -> Tensor<B, 4> {
    let precision = precision.attention();
    let [_, _, lq, _] = q.dims();
    let lk = k.dims()[2];
    match tiled_for::<B>() {
        Some(tiled) if mask.is_none() && lk >= MIN_TILED_KEYS && (!causal || lk >= lq) => {
            tiled(q, k, v, causal, precision)
        }
        // The training backends differentiate burn's decomposition; the shift by each row's maximum
        // needs no gradient (`masked.rs`).
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
) -> Tensor<B, 4> {
    let [_, heads, lq, _] = q.dims();
    let lk = kv.dims()[1];
    match kv::kv_for::<B>() {
        Some(f) if one_operation(mask.is_none(), lq, lk, causal) => f(q, kv, causal, precision.attention()),
        _ => {
            let (k, v) = split_kv(kv, heads);
            attend(q, k, v, mask, causal, precision)
        }
    }
}

/// Whether [`attend_kv`] runs `lq` queries over `lk` keys as one operation on the training backend `B`
/// (whose operands it casts to the attention's format itself, so that they may come in that format).
pub(crate) fn attends_kv_in_one<B: Backend>(unmasked: bool, lq: usize, lk: usize, causal: bool) -> bool {
    kv::kv_for::<B>().is_some() && one_operation(unmasked, lq, lk, causal)
}

/// The shapes [`attend_kv`]'s one operation takes: no mask, long key sequences, and under a causal mask
/// at least as many keys as queries.
fn one_operation(unmasked: bool, lq: usize, lk: usize, causal: bool) -> bool {
    unmasked && lk >= MIN_TILED_KEYS && (!causal || lk >= lq)
}

/// The signature of an attention function on backend `B`.
type AttentionFn<B> = fn(Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>, bool, Precision) -> Tensor<B, 4>;

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

/// A float primitive as a tensor of rank `D`.
pub(crate) fn float<B: Backend, const D: usize>(t: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

/// Query rows per block in training: as many as keep one block's scores within the block size
/// ([`set_block_bytes`], 1 GiB by default), a multiple of 64.
pub fn block_rows(b: usize, h: usize, lq: usize, lk: usize) -> usize {
    let per_row = (b * h * lk * 4).max(1);
    let rows = (block_bytes() / per_row).max(64) / 64 * 64;
    rows.min(lq).max(1)
}

/// One block: query rows `[start, end)`, the keys it sees `[0, keys)` and, for causal blocks that need it,
/// the mask of hidden scores.
struct Block<B: Backend> {
    start: usize,
    end: usize,
    keys: usize,
    hidden: Option<Tensor<B, 4, Bool>>,
}

fn blocks<B: Backend>(lq: usize, lk: usize, rows: usize, causal: bool, dev: &B::Device) -> Vec<Block<B>> {
    let off = lk - lq.min(lk);
    (0..lq)
        .step_by(rows)
        .map(|start| {
            let end = (start + rows).min(lq);
            if !causal {
                return Block {
                    start,
                    end,
                    keys: lk,
                    hidden: None,
                };
            }
            // Query i sees keys j ≤ i + off; the block's last row sees the most.
            let keys = (end + off).min(lk);
            let needs_mask = start + off < keys - 1;
            let hidden = needs_mask.then(|| {
                Tensor::<B, 2, Bool>::tril_mask([end - start, keys], (start + off) as i64, dev)
                    .unsqueeze::<4>()
            });
            Block {
                start,
                end,
                keys,
                hidden,
            }
        })
        .collect()
}

/// `q`, `k` and `v` in the format of the products.
fn operands<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    p: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>) {
    (operand(q, p), operand(k, p), operand(v, p))
}

/// Scaled scores of one block in f32, hidden entries at −∞: `[b, h, rows, keys]`, and the block's queries.
fn scores<B: Backend>(
    q: &Tensor<B, 4>,
    k: &Tensor<B, 4>,
    blk: &Block<B>,
    scale: f64,
    precision: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let qi = q.clone().narrow(2, blk.start, blk.end - blk.start);
    let kr = k.clone().narrow(2, 0, blk.keys);
    let s = matmul(qi.clone(), kr.swap_dims(2, 3), precision).mul_scalar(scale);
    let s = match &blk.hidden {
        Some(m) => {
            let shape = s.shape();
            s.mask_fill(m.clone().expand(shape), f32::NEG_INFINITY)
        }
        None => s,
    };
    (s, qi)
}

/// Forward pass in blocks of `rows` queries: the output `[b, h, lq, dv]` and each row's log-sum-exp of the
/// scaled scores `[b, h, lq, 1]`.
pub fn tiled_forward<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    causal: bool,
    rows: usize,
    precision: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let [_, _, lq, d] = q.dims();
    let lk = k.dims()[2];
    let scale = 1.0 / (d as f64).sqrt();
    // Cast once, not per block (a no-op for operands already in `precision`'s format).
    let (q, k, v) = operands(q, k, v, precision);
    let (mut outs, mut lses) = (Vec::new(), Vec::new());
    for blk in blocks::<B>(lq, lk, rows.max(1), causal, &q.device()) {
        let (s, _) = scores(&q, &k, &blk, scale, precision);
        let m = s.clone().max_dim(3);
        let p = (s - m.clone()).exp();
        let l = p.clone().sum_dim(3);
        outs.push(matmul(p, v.clone().narrow(2, 0, blk.keys), precision) / l.clone());
        lses.push(m + l.log());
    }
    (Tensor::cat(outs, 2), Tensor::cat(lses, 2))
}

/// Rowsum(dO ∘ O) = Σ_j P_ij dP_ij, the softmax Jacobian's correction term of each query (`[b, h, lq, 1]`,
/// f32 whatever the formats of the output's gradient and the output, both of which may be bf16).
pub(crate) fn softmax_delta<B: Backend>(dout: Tensor<B, 4>, out: Tensor<B, 4>) -> Tensor<B, 4> {
    (dout.cast(FloatDType::F32) * out.cast(FloatDType::F32)).sum_dim(3)
}

/// Backward pass in blocks of `rows` queries: gradients of `q`, `k` and `v` from the output's gradient `dout`, recomputing each block's
/// probabilities from `lse`.
#[allow(clippy::too_many_arguments)]
pub fn tiled_backward<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    out: Tensor<B, 4>,
    lse: Tensor<B, 4>,
    dout: Tensor<B, 4>,
    causal: bool,
    rows: usize,
    precision: Precision,
) -> (Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>) {
    let [b, h, lq, d] = q.dims();
    let lk = k.dims()[2];
    let scale = 1.0 / (d as f64).sqrt();
    let delta = softmax_delta(dout.clone(), out);
    let mut dk = Tensor::<B, 4>::zeros(k.shape(), &k.device());
    let mut dv = Tensor::<B, 4>::zeros(v.shape(), &v.device());
    let (q, k, v) = operands(q, k, v, precision);
    let dout = operand(dout, precision);
    let mut dqs = Vec::new();
    for blk in blocks::<B>(lq, lk, rows.max(1), causal, &q.device()) {
        let rows = blk.end - blk.start;
        let (s, qi) = scores(&q, &k, &blk, scale, precision);
        let p = (s - lse.clone().narrow(2, blk.start, rows)).exp();
        let doi = dout.clone().narrow(2, blk.start, rows);
        let kr = k.clone().narrow(2, 0, blk.keys);
        let vr = v.clone().narrow(2, 0, blk.keys);
        let dp = matmul(doi.clone(), vr.swap_dims(2, 3), precision);
        let ds = p.clone() * (dp - delta.clone().narrow(2, blk.start, rows));
        let dv_r = matmul(p.swap_dims(2, 3), doi, precision);
        let ds = operand(ds, precision);
        let dk_r = matmul(ds.clone().swap_dims(2, 3), qi, precision).mul_scalar(scale);
        dqs.push(matmul(ds, kr, precision).mul_scalar(scale));
        if blk.keys == lk {
            dv = dv + dv_r;
            dk = dk + dk_r;
        } else {
            let keys = [0..b, 0..h, 0..blk.keys];
            dv = dv
                .clone()
                .slice_assign(keys.clone(), dv.slice(keys.clone()) + dv_r);
            dk = dk.clone().slice_assign(keys.clone(), dk.slice(keys) + dk_r);
        }
    }
    (Tensor::cat(dqs, 2), dk, dv)
}

#[derive(Debug)]
struct TiledAttention;

impl<B: FusedAttention> Backward<B, 3> for TiledAttention {
    /// q, k, v, output, log-sum-exp, causal, precision of the products.
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        bool,
        Precision,
    );

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [nq, nk, nv] = ops.parents;
        let dout = float::<B, 4>(grads.consume::<B>(&ops.node));
        let (q, k, v, out, lse, causal, precision) = ops.state;
        let (q, k, v, out, lse) = (float(q), float(k), float(v), float(out), float(lse));
        let (dq, dk, dv) = B::attention_backward(q, k, v, out, lse, dout, causal, precision);
        for (node, g) in [(nq, dq), (nk, dk), (nv, dv)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g.into_primitive().tensor());
            }
        }
    }
}

/// The training attention on `Autodiff<I, C>`: forward through `I`'s [`FusedAttention::attention_forward`]
/// (fused kernels on CUDA, [`tiled_forward`] elsewhere), keeping its inputs, output and log-sum-exp for
/// [`FusedAttention::attention_backward`].
pub fn tiled_autodiff<I: FusedAttention, C: CheckpointStrategy>(
    q: Tensor<Autodiff<I, C>, 4>,
    k: Tensor<Autodiff<I, C>, 4>,
    v: Tensor<Autodiff<I, C>, 4>,
    causal: bool,
    precision: Precision,
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
    let (out, lse) = I::attention_forward(qi.clone(), ki.clone(), vi.clone(), causal, precision);
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
            );
            prep.finish(state, out_p)
        }
        OpsKind::UnTracked(prep) => prep.finish(out_p),
    };
    float(y)
}
