//! The training attention's kernels: `flash2` (FlashAttention-2 in CUDA C) or fused (one cubecl kernel per
//! pass) on CUDA, tiled (FlashAttention's algorithm in backend tensor operations, [`crate::attention`])
//! elsewhere.
//!
//! [`crate::attention`]'s custom autodiff operation computes its forward and backward passes through
//! [`FusedAttention`], a trait of the inner backend. On the CPU (`Flex`) both passes are the tiled ones.
//! On CUDA, with [`AttentionKernel::Flash2`] (the default), each pass is a custom operation in
//! burn-fusion's stream that launches the CUDA C kernels of umgen-cuda's `kernels/flash2/flash2.cu` (compiled with NVRTC, run on
//! cubecl's stream or a side stream: `flash/flash2.rs`), whose products keep scores and probabilities in
//! registers; head sizes other than 32 and 64 run the fused kernels. With [`AttentionKernel::Fused`] each
//! pass launches this module's cubecl kernels (`flash/kernels.rs`): the `lq × lk` scores and
//! probabilities live only in shared memory, so a pass costs its inputs, outputs and one log-sum-exp per
//! query instead of a block of score matrices in global memory, and one launch instead of a few dozen per
//! block. A head size the kernels do not take (not a multiple of 16, or over [`MAX_HEAD`]) runs the tiled
//! passes instead, counted by [`fallbacks`] and logged once.

use crate::format::Precision;
use crate::kernels::Kernels;
pub use crate::kernels::{AttentionKernel, DEFAULT_STEP, STEPS, check_step};
use crate::tiled::{tiled_backward, tiled_forward};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;
use std::sync::atomic::{AtomicUsize, Ordering};

#[cfg(feature = "cuda")]
mod cuda;
#[cfg(feature = "cuda")]
mod flash2;
#[cfg(feature = "cuda")]
mod kernels;

/// The largest head size the fused kernels take (their shared memory grows with it).
pub const MAX_HEAD: usize = 128;

/// Rows of a fused kernel's block (queries, or keys for the key/value gradients).
pub const BLOCK: usize = 64;

/// Row padding (elements) of the buffers the products read, for operands of `elem` bytes: 16 bytes, the
/// least that keeps every tensor-core load on a 32-byte boundary (16-bit fragments also need a row stride
/// of a multiple of 8 elements) while shifting consecutive rows to other banks. Four f32 elements rather
/// than eight save the shared memory that fits a third query-gradient cube on an SM.
pub(crate) const fn pad(elem: usize) -> usize {
    16 / elem
}

/// Row stride (elements) of the kernels' Q, K, V and dO tiles for head size `head` and `elem`-byte
/// operands.
pub(crate) const fn tile_stride(head: usize, elem: usize) -> usize {
    head + pad(elem)
}

/// Row stride of the kernels' f32 score (and score-gradient) buffers for a loop of `step` rows.
pub(crate) const fn score_stride(step: usize) -> usize {
    step + 4
}

/// Row stride of the kernels' probability (and score-gradient) buffers in the products' format.
pub(crate) const fn prob_stride(step: usize, elem: usize) -> usize {
    step + pad(elem)
}

/// Row stride of the kernels' f32 accumulators for head size `head`.
pub(crate) const fn acc_stride(head: usize) -> usize {
    head + 4
}

/// Passes that wanted the fused kernels but ran the tiled ones.
static FALLBACKS: AtomicUsize = AtomicUsize::new(0);
/// How many passes fell back from the fused kernels to the tiled ones in this process.
pub fn fallbacks() -> usize {
    FALLBACKS.load(Ordering::Relaxed)
}

/// Shared memory (bytes) each fused kernel declares for head size `head`, operands of `elem` bytes and a
/// loop of `step` rows: forward, key/value gradients, query gradients. Each holds its own block's tiles,
/// one step's tiles, f32 scores, probabilities in the products' format and f32 accumulators.
pub fn kernel_shared_bytes(head: usize, elem: usize, step: usize) -> [usize; 3] {
    let block = BLOCK * tile_stride(head, elem) * elem;
    let stepped = step * tile_stride(head, elem) * elem;
    let scores = BLOCK * score_stride(step) * 4;
    let probs = BLOCK * prob_stride(step, elem) * elem;
    let acc = BLOCK * acc_stride(head) * 4;
    let forward = block + 2 * stepped + scores + probs + acc;
    let kv = 2 * block + 2 * stepped + 2 * step * 4 + 2 * scores + 2 * probs + 2 * acc;
    let q = 2 * block + 2 * stepped + 2 * scores + probs + acc;
    [forward, kv, q]
}

/// Shared memory (bytes) the largest of the fused kernels declares (the key/value gradients' kernel).
pub fn shared_bytes(head: usize, elem: usize, step: usize) -> usize {
    kernel_shared_bytes(head, elem, step)
        .into_iter()
        .max()
        .unwrap_or(0)
}

/// Why the fused kernels cannot take a head size, if they cannot.
pub fn unfit(head: usize) -> Option<String> {
    (head == 0 || !head.is_multiple_of(16) || head > MAX_HEAD)
        .then(|| format!("head size {head} (the fused kernels take multiples of 16 up to {MAX_HEAD})"))
}

/// Counts a pass that runs other kernels than those chosen (`from`, which refused `why`, to `to`); logs
/// the first.
#[cfg_attr(not(feature = "cuda"), allow(dead_code))]
pub(crate) fn fell_back(from: &str, why: &str, to: &str) {
    if FALLBACKS.fetch_add(1, Ordering::Relaxed) == 0 {
        tracing::warn!("{from} attention refused {why}; the {to} kernels run it (counted in fallbacks)");
    }
}

/// A backend that computes the training attention's two passes. `q: [b, h, lq, d]`, `k`, `v:
/// [b, h, lk, d]`, already in `precision`'s format; `causal` hides keys after each query, bottom-right
/// aligned. The log-sum-exp is f32; the output and the gradients are f32, or in the operands' format where
/// CUDA's flash2 kernels compute them (bf16 for the products that read them next).
pub trait FusedAttention: Backend {
    /// The output `[b, h, lq, d]` and each query's log-sum-exp of its scaled scores `[b, h, lq, 1]`.
    fn attention_forward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>);

    /// The gradients of `q`, `k` and `v` from the output's gradient `dout`, given the forward pass's output
    /// and log-sum-exp.
    #[allow(clippy::too_many_arguments)]
    fn attention_backward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        out: Tensor<Self, 4>,
        lse: Tensor<Self, 4>,
        dout: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>, Tensor<Self, 4>);

    /// [`Self::attention_backward`] with the keys' and values' gradients as one `[b, lk, 2·h·d]` (the keys'
    /// columns, then the values'): the layout of a kv product's gradient (`attention/kv.rs`, the recomputed
    /// layers). CUDA's flash2 kernels write it so; elsewhere `merge_kv` copies the two into it.
    #[allow(clippy::too_many_arguments)]
    fn attention_backward_kv(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        out: Tensor<Self, 4>,
        lse: Tensor<Self, 4>,
        dout: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 3>) {
        let (dq, dk, dv) = Self::attention_backward(q, k, v, out, lse, dout, causal, precision, kernels);
        (dq, merge_kv(dk, dv))
    }
}

/// `dk` and `dv` `[b, h, lk, d]` as one `[b, lk, 2·h·d]`: the keys' columns, then the values'.
pub(crate) fn merge_kv<B: Backend>(dk: Tensor<B, 4>, dv: Tensor<B, 4>) -> Tensor<B, 3> {
    let [b, h, lk, d] = dk.dims();
    Tensor::stack::<5>(vec![dk.swap_dims(1, 2), dv.swap_dims(1, 2)], 2).reshape([b, lk, 2 * h * d])
}

/// The tiled forward pass in blocks of `kernels.attention_block_mib`.
pub(crate) fn tiled_forward_pass<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let [b, h, lq, _] = q.dims();
    let rows = crate::tiled::block_rows(b, h, lq, k.dims()[2], kernels.block_bytes());
    tiled_forward(q, k, v, causal, rows, precision)
}

/// The tiled backward pass in blocks of `kernels.attention_block_mib`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn tiled_backward_pass<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    out: Tensor<B, 4>,
    lse: Tensor<B, 4>,
    dout: Tensor<B, 4>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> (Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>) {
    let [b, h, lq, _] = q.dims();
    let rows = crate::tiled::block_rows(b, h, lq, k.dims()[2], kernels.block_bytes());
    tiled_backward(q, k, v, out, lse, dout, causal, rows, precision)
}

/// The CPU has the tiled passes only; CPU training runs them through the same autodiff operation.
impl FusedAttention for burn::backend::Flex {
    fn attention_forward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>) {
        tiled_forward_pass(q, k, v, causal, precision, kernels)
    }

    fn attention_backward(
        q: Tensor<Self, 4>,
        k: Tensor<Self, 4>,
        v: Tensor<Self, 4>,
        out: Tensor<Self, 4>,
        lse: Tensor<Self, 4>,
        dout: Tensor<Self, 4>,
        causal: bool,
        precision: Precision,
        kernels: &Kernels,
    ) -> (Tensor<Self, 4>, Tensor<Self, 4>, Tensor<Self, 4>) {
        tiled_backward_pass(q, k, v, out, lse, dout, causal, precision, kernels)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn head_sizes_the_kernels_take() {
        for ok in [16, 64, 128] {
            assert!(unfit(ok).is_none(), "{ok}");
        }
        for bad in [0, 8, 24, 65, 144] {
            let why = unfit(bad).expect("refused");
            assert!(why.contains(&bad.to_string()), "{why}");
        }
    }

    #[test]
    fn shared_memory_decides_how_many_cubes_share_an_sm() {
        // Cubes per SM of 228 KB, each also reserving 1 KB.
        let per_sm = |bytes: usize| 233_472 / (bytes + 1024);
        // Head size 64 in f32 with steps of 16 (the default): two key/value cubes, three query-gradient
        // cubes, four forward cubes. (Nsight Compute, with rows padded by 8 floats
        // instead of 4: 103.55, 79.87 and 56.32 KB, so two query-gradient cubes.)
        assert_eq!(kernel_shared_bytes(64, 4, 16), [53_760, 98_944, 76_288]);
        assert_eq!(kernel_shared_bytes(64, 4, 16).map(per_sm), [4, 2, 3]);
        // With steps of 64 (the kernels before), one cube of each backward kernel (the key/value one: Nsight
        // reported 180.74 KB with the wider padding).
        assert_eq!(kernel_shared_bytes(64, 4, 64).map(per_sm)[1..], [1, 1]);
        // An H200 refused the f32 kernels at head size 128 with steps of 64 ("Requested 279040 bytes,
        // maximum 232448", the wider padding); they still do not fit, and do with shorter steps.
        assert!(shared_bytes(128, 4, 64) > 232_448 && shared_bytes(128, 4, 32) <= 232_448);
        // bf16 operands keep 8-element padding (16-bit fragments need strides of multiples of 8).
        assert_eq!(tile_stride(64, 2), 72);
        assert!(shared_bytes(128, 2, 64) <= 232_448);
    }
}
