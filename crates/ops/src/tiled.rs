//! FlashAttention's algorithm written with backend tensor operations: the forward pass walks blocks of
//! queries, keeps only the output and each row's log-sum-exp, and the backward pass recomputes every block's
//! probabilities from them (FlashAttention-2, Dao 2023, algorithm 2). Causal blocks stop at their last
//! visible key, which also halves the matrix work. Memory is O(b·h·block·lk) instead of O(b·h·lq·lk).
//! [`crate::attention`] runs these passes as one autodiff operation on the CPU, and the fused kernels'
//! passes ([`crate::flash`]) fall back to them.

use crate::format::{Precision, matmul, operand};
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, FloatDType, Tensor};

/// Shorter key sequences take the decomposed path: their score matrices are no larger than a few copies of
/// the keys, and the block loop only adds launches (H200, `umgen-kernel-bench attention`: 70,352 sequences of 8
/// tokens took 15.8 ms tiled against 8.1 ms decomposed; 32 × 6 heads × 2,199 causal tokens 34 ms against
/// 101 ms, in 3.4 GiB instead of 29.6).
pub const MIN_TILED_KEYS: usize = 256;

/// Query rows per block in training: as many as keep one block's scores within `block_bytes`
/// ([`crate::Kernels::block_bytes`], 1 GiB by default), a multiple of 64.
pub fn block_rows(b: usize, h: usize, lq: usize, lk: usize, block_bytes: usize) -> usize {
    let per_row = (b * h * lk * 4).max(1);
    let rows = (block_bytes / per_row).max(64) / 64 * 64;
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
pub(crate) fn operands<B: Backend>(
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
pub fn softmax_delta<B: Backend>(dout: Tensor<B, 4>, out: Tensor<B, 4>) -> Tensor<B, 4> {
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
