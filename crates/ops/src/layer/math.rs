//! A pre-norm attention layer's forward and backward passes written out on a backend without autodiff: a
//! self-attention layer, or a cross-attention layer whose keys and values come from a context of its own
//! (`x + attn(ln1(x), ln_ctx(ctx))`, then the MLP).
//!
//! [`super`] runs a layer as one operation that keeps either its inputs alone, recomputing the rest in the
//! backward pass, or the activations its backward pass reads ([`Keep`]). burn 0.21 cannot run a
//! recomputation under autodiff: a backward pass started inside another one deadlocks on the graph
//! client's locks (`GraphMutexClient::backward` locks every graph when it cleans up, the outer one
//! included). So the layer's gradients are derived here by hand, with the same kernels as the autodiff
//! path (the named matmul, the fused or tiled attention, the MLP's bias + GELU) and the same casts for
//! [`Precision::Bf16`], so that both paths give the same numbers to rounding. Written out, the gradients
//! that meet on one tensor are summed by the kernel that writes the second (the residual stream's by the
//! norm's backward kernel, the normalised input's by the key-value product's epilogue), where burn's
//! autodiff adds them in element-wise kernels of their own.

mod pieces;

use crate::flash::merge_kv;
use crate::format::Precision;
use crate::format::{float_format, operand};
use crate::gelu::{inner_backward, inner_forward, inner_product_dtype};
use crate::heads::{merge_heads, split_heads};
use crate::kernels::Kernels;
use crate::tiled::{MIN_TILED_KEYS, tiled_backward, tiled_forward};
use burn::tensor::{FloatDType, Tensor, TensorPrimitive};
pub use pieces::{LayerBackend, Lin, Mask, Norm};
use pieces::{Stats, drop, linear_grad, linear_in, norm, norm_grad, product_grad, residual, unbiased};

/// The parameters of `SelfBlock` or `CrossBlock`, in the order of the operation's parents and of
/// [`WeightGrads`].
#[derive(Debug, Clone)]
pub struct Weights<I: LayerBackend> {
    /// The norm of the queries (and, in a self-attention layer, of the keys and values).
    pub ln1: Norm<I>,
    /// A cross-attention layer's norm of its context; `None` in a self-attention layer.
    pub ln_ctx: Option<Norm<I>>,
    pub q: Lin<I>,
    pub kv: Lin<I>,
    pub proj: Lin<I>,
    pub ln2: Norm<I>,
    pub fc: Lin<I>,
    pub out: Lin<I>,
}

/// One gradient per parameter, in the same order as the parameters.
pub type WeightGrads<I> = Vec<TensorPrimitive<I>>;

/// Shape-independent settings of the layer.
#[derive(Debug, Clone, Copy)]
pub struct Setting {
    pub heads: usize,
    pub causal: bool,
    pub precision: Precision,
    /// Layer norms' ε (burn's default, which `layers.rs` builds with).
    pub eps: f64,
    /// `Some((t, n))` for a TAR temporal layer on the rows as they lie: the input `[b, t · n, d]` is `t`
    /// frames of `n` positions, and each position attends over its own frames (`crate::temporal`'s
    /// kernels, as the layer without recomputation runs them) instead of the rows over each other.
    pub over_time: Option<(usize, usize)>,
    /// The kernels of every pass.
    pub kernels: Kernels,
}

/// Dropout masks of the attention and MLP outputs.
#[derive(Debug, Clone)]
pub struct Masks<I: LayerBackend> {
    pub attn: Mask<I>,
    pub mlp: Mask<I>,
}

/// What the backward pass reads of the forward pass: the activations a kept layer holds from its
/// forward pass until its backward pass, or a recomputed layer's, recomputed there.
#[derive(Debug, Clone)]
pub struct Saved<I: LayerBackend> {
    /// The input as the first norm's backward pass reads it: in the format `keep` names, else as given.
    x: Tensor<I, 3>,
    stats1: Stats<I>,
    n1: Tensor<I, 3>,
    /// A cross-attention layer's context, its norm's statistics and the normalised context.
    ctx: Option<(Tensor<I, 3>, Stats<I>, Tensor<I, 3>)>,
    attn: Attn<I>,
    merged: Tensor<I, 3>,
    /// The residual stream after the attention, as the second norm's backward pass reads it (in the
    /// format `keep` names where [`Keep::all`]).
    x1: Tensor<I, 3>,
    stats2: Stats<I>,
    n2: Tensor<I, 3>,
    /// The MLP's first product, without its bias (what the bias + GELU's backward pass reads).
    hidden: Tensor<I, 2>,
    /// The MLP's activation; `None` where the backward pass recomputes it from `hidden`
    /// (`train.kernels.recompute_gelu` in a kept layer).
    act: Option<Tensor<I, 3>>,
}

/// What a forward pass keeps of the residual stream for the backward pass.
#[derive(Debug, Clone, Copy)]
pub struct Keep {
    /// The format the norms' inputs are kept in where it is not theirs (`train.kernels.kept_inputs`),
    /// written by the norms' kernels as they read them.
    pub format: Option<FloatDType>,
    /// Keep the second norm's input in that format too: the layer keeps its activations (the
    /// recomputation writes it afresh).
    pub all: bool,
}

impl Keep {
    /// What the recomputation in the backward pass keeps: nothing beyond what it reads.
    pub const NOTHING: Self = Self {
        format: None,
        all: false,
    };
}

/// What the attention's backward pass reads.
#[derive(Debug, Clone)]
enum Attn<I: LayerBackend> {
    /// The rows over each other: queries, keys and values split into heads (in the attention's format), the
    /// output and the log-sum-exp.
    Rows([Tensor<I, 4>; 5]),
    /// Each position over its own frames: queries `[b, t, n, d]`, keys and values `[b, t, n, 2d]`, the
    /// output and the log-sum-exp.
    OverTime([Tensor<I, 4>; 4]),
}

/// Attention of `q` over `k`, `v` (already in the products' format): the output and each query's
/// log-sum-exp. Short key sequences (the TAR's sequences over time) take one decomposed block, as
/// `attention::attend` sends them to burn's decomposed attention: the fused kernels would spend a cube of 64
/// rows on each of their tens of thousands of 8- or 20-token sequences.
fn attend<I: LayerBackend>(
    q: Tensor<I, 4>,
    k: Tensor<I, 4>,
    v: Tensor<I, 4>,
    s: Setting,
) -> (Tensor<I, 4>, Tensor<I, 4>) {
    let lq = q.dims()[2];
    if k.dims()[2] >= MIN_TILED_KEYS {
        I::attention_forward(q, k, v, s.causal, s.precision.attention(), &s.kernels)
    } else {
        tiled_forward(q, k, v, s.causal, lq, s.precision.attention())
    }
}

/// [`attend`]'s gradients of `q` and of `k` and `v` as one `[b, lk, 2·h·d]` (the kv product's layout).
#[allow(clippy::too_many_arguments)]
fn attend_grad<I: LayerBackend>(
    q: Tensor<I, 4>,
    k: Tensor<I, 4>,
    v: Tensor<I, 4>,
    out: Tensor<I, 4>,
    lse: Tensor<I, 4>,
    dout: Tensor<I, 4>,
    s: Setting,
) -> (Tensor<I, 4>, Tensor<I, 3>) {
    let lq = q.dims()[2];
    if k.dims()[2] >= MIN_TILED_KEYS {
        I::attention_backward_kv(
            q,
            k,
            v,
            out,
            lse,
            dout,
            s.causal,
            s.precision.attention(),
            &s.kernels,
        )
    } else {
        let (dq, dk, dv) = tiled_backward(q, k, v, out, lse, dout, s.causal, lq, s.precision.attention());
        (dq, merge_kv(dk, dv))
    }
}

/// The layer for input `x` `[b, l, d]` (and a cross-attention layer's context `ctx` `[b, lk, d]`) up to its
/// last product: the residual stream after the attention half, the MLP's activation, and what the
/// backward pass reads (`keep` says in which formats). The backward pass needs nothing of the output
/// product, so only [`forward`] runs it.
fn run<I: LayerBackend>(
    w: &Weights<I>,
    s: Setting,
    masks: &Masks<I>,
    x: Tensor<I, 3>,
    ctx: Option<Tensor<I, 3>>,
    keep: Keep,
) -> (Tensor<I, 3>, Tensor<I, 3>, Saved<I>) {
    let (p, k) = (s.precision, &s.kernels);
    // The normalised inputs and the merged attention output feed products only: in their format once here
    // (the norms write it), not cast by each product (the forward pass's two, the recomputation's two and
    // the weight gradients').
    let (n1, stats1, kept) = norm(x.clone(), &w.ln1, s.eps, p, keep.format, k);
    // Over positions the queries, keys and values are the attention's operands: written in its format
    // (the attention over time reads f32).
    let qkv_format = match s.over_time {
        None => p.attention().operand_dtype(),
        Some(_) => FloatDType::F32,
    };
    let ctx = match (ctx, &w.ln_ctx) {
        (Some(c), Some(ln)) => {
            let (nc, stats, _) = norm(c.clone(), ln, s.eps, p, None, k);
            Some((c, stats, nc))
        }
        _ => None,
    };
    let q = linear_in(n1.clone(), &w.q, p, qkv_format, k);
    let kv = match &ctx {
        // From the normalised context as `MultiHead::forward` has them: in f32 with the bias, then rounded
        // once to the attention's format (written in it by the product and rounded again after the bias,
        // a stack's context gradient came out twice as far from f32's as the autodiff path's).
        Some((_, _, nc)) => operand(linear_in(nc.clone(), &w.kv, p, FloatDType::F32, k), p.attention()),
        None => linear_in(n1.clone(), &w.kv, p, qkv_format, k),
    };
    let [b, len, d] = q.dims();
    let (attn, merged) = match s.over_time {
        None => {
            // Already in the attention's format; flash2 reads the heads' strided views.
            let q = split_heads(q, s.heads);
            let k = split_heads(kv.clone().narrow(2, 0, d), s.heads);
            let v = split_heads(kv.narrow(2, d, d), s.heads);
            let (att, lse) = attend(q.clone(), k.clone(), v.clone(), s);
            let merged = merge_heads(att.clone());
            (Attn::Rows([q, k, v, att, lse]), merged)
        }
        Some((t, n)) => {
            let (q, kv) = (q.reshape([b, t, n, d]), kv.reshape([b, t, n, 2 * d]));
            let (att, lse) = I::temporal_forward(q.clone(), kv.clone(), s.heads, s.causal, p, k);
            let merged = att.clone().reshape([b, len, d]);
            (Attn::OverTime([q, kv, att, lse]), merged)
        }
    };
    let merged = operand(merged, p);
    let x1 = residual(x.clone(), &masks.attn, merged.clone(), &w.proj, p, k);
    let keep2 = keep.format.filter(|_| keep.all);
    let (n2, stats2, kept2) = norm(x1.clone(), &w.ln2, s.eps, p, keep2, k);
    let hidden = unbiased(n2.clone(), &w.fc, p, inner_product_dtype(p, k), k);
    let act = activation(&hidden, &w.fc, n2.dims(), k);
    let saved = Saved {
        x: kept.unwrap_or(x),
        stats1,
        n1,
        ctx,
        attn,
        merged,
        x1: kept2.unwrap_or_else(|| x1.clone()),
        stats2,
        n2,
        hidden,
        act: None,
    };
    (x1, act, saved)
}

/// The MLP's activation `gelu(hidden + b)` `[b, l, inner]` for its input's dims `[b, l, _]`.
fn activation<I: LayerBackend>(
    hidden: &Tensor<I, 2>,
    fc: &Lin<I>,
    [b, len, _]: [usize; 3],
    k: &Kernels,
) -> Tensor<I, 3> {
    inner_forward(hidden.clone(), fc.b.clone(), k).reshape([b, len, hidden.dims()[1]])
}

/// The layer's output for input `x` `[b, l, d]` (over the context `ctx` in a cross-attention layer) and
/// what its backward pass reads: with [`Keep::all`] every activation ([`gradients`] reads them), else
/// the input alone (in `keep.format` where given, written by the first norm's kernel as it reads `x`),
/// from which [`backward`] recomputes the rest.
pub fn forward<I: LayerBackend>(
    w: &Weights<I>,
    s: Setting,
    masks: &Masks<I>,
    x: Tensor<I, 3>,
    ctx: Option<Tensor<I, 3>>,
    keep: Keep,
) -> (Tensor<I, 3>, Kept<I>) {
    let (x1, act, mut f) = run(w, s, masks, x, ctx, keep);
    if keep.all && !s.kernels.recompute_gelu {
        f.act = Some(act.clone());
    }
    let y = residual(x1, &masks.mlp, act, &w.out, s.precision, &s.kernels);
    let kept = if keep.all {
        Kept::Activations(Box::new(f))
    } else {
        Kept::Input(f.x)
    };
    (y, kept)
}

/// What a layer's forward pass keeps for its backward pass.
#[derive(Debug, Clone)]
pub enum Kept<I: LayerBackend> {
    /// The input alone (recomputation).
    Input(Tensor<I, 3>),
    /// Every activation the backward pass reads.
    Activations(Box<Saved<I>>),
}

/// The gradients of the input, of a cross-attention layer's context and of every parameter from the
/// output's gradient `dy`, recomputing the forward pass from `x` (f32, or the copy [`forward`] kept) and
/// `ctx` with the forward pass's dropout masks.
pub fn backward<I: LayerBackend>(
    w: &Weights<I>,
    s: Setting,
    masks: &Masks<I>,
    (x, ctx): (Tensor<I, 3>, Option<Tensor<I, 3>>),
    dy: Tensor<I, 3>,
) -> (Tensor<I, 3>, Option<Tensor<I, 3>>, WeightGrads<I>) {
    let (_, act, f) = run(w, s, masks, x, ctx, Keep::NOTHING);
    let f = Saved { act: Some(act), ..f };
    gradients(w, s, masks, f, dy)
}

/// The gradients of [`backward`] from the activations `f` of the forward pass (kept, or recomputed).
pub fn gradients<I: LayerBackend>(
    w: &Weights<I>,
    s: Setting,
    masks: &Masks<I>,
    f: Saved<I>,
    dy: Tensor<I, 3>,
) -> (Tensor<I, 3>, Option<Tensor<I, 3>>, WeightGrads<I>) {
    let (p, k) = (s.precision, &s.kernels);
    let d_out = drop(&masks.mlp, dy.clone());
    let act = match f.act {
        Some(a) => a,
        None => activation(&f.hidden, &w.fc, f.n2.dims(), k),
    };
    // The activation's gradient in its own format (bf16 with the bf16 presets), as `mlp::gelu_mlp` has it.
    let act_format = float_format(act.dtype());
    let (d_act, d_out_w, d_out_b) = linear_grad(act, &w.out, d_out, (p, act_format), None, k);
    let d_act = d_act.reshape(f.hidden.dims());
    let (d_hidden, d_fc_b) = inner_backward(d_act, f.hidden, w.fc.b.clone(), k);
    let (dn2, d_fc_w) = product_grad(f.n2, &w.fc, d_hidden, (p, FloatDType::F32), None, k);
    // The residual stream's gradient added to the norm's by its kernel.
    let (dx1, d_ln2_g, d_ln2_b) = norm_grad(f.x1, f.stats2, &w.ln2, dn2, Some(dy), k);
    let d_proj = drop(&masks.attn, dx1.clone());
    // The attention's output gradient in the output's own format: bf16 where flash2 wrote it so, which
    // its backward pass then reads without a cast.
    let d_merged_format = match &f.attn {
        Attn::Rows([.., att, _]) => float_format(att.dtype()),
        Attn::OverTime(_) => FloatDType::F32,
    };
    let (d_merged, d_proj_w, d_proj_b) =
        linear_grad(f.merged, &w.proj, d_proj, (p, d_merged_format), None, k);
    let (dq, dkv) = match f.attn {
        Attn::Rows([q, k, v, att, lse]) => {
            let (dq, dkv) = attend_grad(q, k, v, att, lse, split_heads(d_merged, s.heads), s);
            (merge_heads(dq), dkv)
        }
        Attn::OverTime([q, kv, att, lse]) => {
            let [b, t, n, d] = q.dims();
            let saved = I::KEEPS_FORWARD.then_some((att, lse));
            let dout = d_merged.reshape([b, t, n, d]);
            let (dq, dkv) = I::temporal_backward(q, kv, saved, dout, s.heads, s.causal, p, k);
            (dq.reshape([b, t * n, d]), dkv.reshape([b, t * n, 2 * d]))
        }
    };
    let (dn1_q, d_q_w, d_q_b) = linear_grad(f.n1.clone(), &w.q, dq, (p, FloatDType::F32), None, k);
    let one = |t: Tensor<I, 1>| t.into_primitive();
    let two = |t: Tensor<I, 2>| t.into_primitive();
    // The keys' and values' input: the normalised context of a cross-attention layer, else the queries'.
    let (d_kv_w, d_kv_b, dn1, dctx) = match (f.ctx, &w.ln_ctx) {
        (Some((c, stats, nc)), Some(ln)) => {
            let (dnc, d_kv_w, d_kv_b) = linear_grad(nc, &w.kv, dkv, (p, FloatDType::F32), None, k);
            let (dctx, dg, db) = norm_grad(c, stats, ln, dnc, None, k);
            (d_kv_w, d_kv_b, dn1_q, Some((dctx, [one(dg), one(db)])))
        }
        _ => {
            // The queries' part of the input's gradient summed by the second product's epilogue.
            let (dn1, d_kv_w, d_kv_b) = linear_grad(f.n1, &w.kv, dkv, (p, FloatDType::F32), Some(dn1_q), k);
            (d_kv_w, d_kv_b, dn1, None)
        }
    };
    let (dx, d_ln1_g, d_ln1_b) = norm_grad(f.x, f.stats1, &w.ln1, dn1, Some(dx1), k);
    let (dctx, d_ln_ctx) = dctx.unzip();
    let grads = [one(d_ln1_g), one(d_ln1_b)]
        .into_iter()
        .chain(d_ln_ctx.into_iter().flatten())
        .chain([
            two(d_q_w),
            one(d_q_b),
            two(d_kv_w),
            one(d_kv_b),
            two(d_proj_w),
            one(d_proj_b),
            one(d_ln2_g),
            one(d_ln2_b),
            two(d_fc_w),
            one(d_fc_b),
            two(d_out_w),
            one(d_out_b),
        ])
        .collect();
    (dx, dctx, grads)
}
