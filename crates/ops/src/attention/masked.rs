//! Attention by burn's operations with the rows' maximum detached, for the training backends' attention
//! calls that the tiled operation does not take (a mask, or fewer keys than [`crate::tiled::MIN_TILED_KEYS`]).
//!
//! burn's `attention_fallback` shifts each row of scores by its maximum (`max_dim`) before the exponential,
//! and burn's autodiff differentiates through the shift: `max_dim`'s backward pass scatters the maximum's
//! gradient into a zero tensor of the scores' shape. The softmax does not depend on the shift, so that
//! gradient cancels in the sum, yet its scatter took 0.68 ms for each of the ego module's four masked
//! cross-attention layers in a `small` step (H100 timeline, docs/decisions/007-memory-bound-training-kernels.md). Here the shift is taken
//! from the detached scores; forward values are burn's, operation for operation.

use burn::tensor::backend::Backend;
use burn::tensor::{Bool, Tensor};

/// `softmax(q kᵀ / √d) v` over `[b, h, l, d]` tensors, hiding the keys `mask` marks (true = hidden, `[b,
/// h, lq, lk]`) and, when `causal`, the keys after each query (bottom-right aligned, as burn's
/// `is_causal`). A fully hidden row gives zeros, as in burn's fallback.
pub(crate) fn attention_shift_detached<B: Backend>(
    q: Tensor<B, 4>,
    k: Tensor<B, 4>,
    v: Tensor<B, 4>,
    mask: Option<Tensor<B, 4, Bool>>,
    causal: bool,
) -> Tensor<B, 4> {
    let [b, h, lq, d] = q.dims();
    let lk = k.dims()[2];
    let mut s = q.matmul(k.swap_dims(2, 3)).mul_scalar(1.0 / (d as f64).sqrt());
    if let Some(mask) = mask {
        s = s.mask_fill(mask, f32::NEG_INFINITY);
    }
    if causal {
        let offset = lk as i64 - lq as i64;
        let hidden =
            Tensor::<B, 4, Bool>::tril_mask([1, 1, lq, lk], offset, &s.device()).expand([b, h, lq, lk]);
        s = s.mask_fill(hidden, f32::NEG_INFINITY);
    }
    // Clamped as burn's fallback clamps them, so that a row with every key hidden gives 0 and not NaN.
    let shift = s.clone().detach().max_dim(3).clamp_min(f32::MIN);
    let e = (s - shift).exp();
    let sum = e.clone().sum_dim(3).clamp_min(f32::MIN_POSITIVE);
    (e / sum).matmul(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::tensor::module::attention;
    use burn::tensor::ops::AttentionModuleOptions;
    use burn::tensor::{Distribution, TensorData};

    type A = Autodiff<Flex>;

    fn random(dims: [usize; 4]) -> Tensor<A, 4> {
        Tensor::random(dims, Distribution::Normal(0.0, 1.0), &Default::default()).require_grad()
    }

    fn max_diff(a: Tensor<Flex, 4>, b: Tensor<Flex, 4>) -> f32 {
        (a - b).abs().max().into_scalar()
    }

    /// Output and the gradients of q, k and v equal burn's fallback, masked (a fully hidden row among
    /// them) and causal with more keys than queries.
    #[test]
    fn matches_burns_attention_and_its_gradients() {
        let dev = Default::default();
        for causal in [false, true] {
            let (q, k, v) = (random([2, 3, 5, 4]), random([2, 3, 7, 4]), random([2, 3, 7, 4]));
            // Row 1 of every head hides all of its keys; elsewhere every third key.
            let hidden: Vec<bool> = (0..2 * 3 * 5 * 7)
                .map(|i| (i / 7) % 5 == 1 || i % 3 == 0)
                .collect();
            let mask = Tensor::<A, 4, Bool>::from_data(TensorData::new(hidden, [2, 3, 5, 7]), &dev);
            let w = Tensor::<A, 4>::random([2, 3, 5, 4], Distribution::Normal(0.0, 1.0), &dev);
            let opts = AttentionModuleOptions {
                is_causal: causal,
                ..Default::default()
            };
            let ours = attention_shift_detached(q.clone(), k.clone(), v.clone(), Some(mask.clone()), causal);
            let theirs = attention(q.clone(), k.clone(), v.clone(), Some(mask), None, opts);
            assert!(max_diff(ours.clone().inner(), theirs.clone().inner()) < 1e-6);
            let g_ours = (ours * w.clone()).sum().backward();
            let g_theirs = (theirs * w).sum().backward();
            for x in [&q, &k, &v] {
                let (a, b) = (x.grad(&g_ours).expect("grad"), x.grad(&g_theirs).expect("grad"));
                let d = max_diff(a, b);
                assert!(d < 1e-5, "gradient {d} apart (causal {causal})");
            }
        }
    }
}
