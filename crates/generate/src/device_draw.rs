//! Drawing tokens on the model's device, one draw per row of a batch of logits, without reading them
//! back: Gumbel-max over the top-k (found on the device) with uniform numbers from the host's seeded
//! generator.

use crate::sampling::Sampling;
use burn::tensor::activation::softmax;
use burn::tensor::backend::Backend;
use burn::tensor::{IndexingUpdateOp, Int, Tensor, TensorData};
use rand::Rng;

/// How the device finds each row's `k` largest logits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceTopK {
    /// `k` rounds of argmax, gather and masking: about `3k` small kernels, on every backend.
    #[default]
    Rounds,
    /// burn's `argtopk`, one reduction kernel on burn-cubecl (cubek's `ArgTopK`, largest first), then a
    /// gather. Not on the CPU backends (Flex and ndarray leave it unimplemented).
    Reduce,
}

impl DeviceTopK {
    /// The `k` largest entries of each row of `x` `[m, v]` and their ids `[m, k]`, largest first.
    pub fn rows<B: Backend>(self, x: Tensor<B, 2>, k: usize) -> (Tensor<B, 2>, Tensor<B, 2, Int>) {
        match self {
            Self::Rounds => top_k_rows(x, k),
            Self::Reduce => {
                let ids = x.clone().argtopk(k, 1);
                (x.gather(1, ids.clone()), ids)
            }
        }
    }
}

impl Sampling {
    /// One draw per row of `logits` (`[m, v]`) on their device, with the distribution of [`Self::draw`]
    /// (top-k, temperature, top-p; −∞ is never drawn; rows must hold no NaN). Nothing is read back to
    /// the host, so the ids can feed the next decoding step directly. Gumbel-max: the argmax of the
    /// filtered, tempered logits plus Gumbel noise is a draw from their softmax. The uniform numbers come
    /// from `rng` and are uploaded (`m × min(top_k, v)` of them), not from the backend's generator, which
    /// is one per process: draws stay a function of the seed whatever else runs.
    pub fn draw_rows<B: Backend>(&self, logits: Tensor<B, 2>, rng: &mut impl Rng) -> Tensor<B, 1, Int> {
        let [m, v] = logits.dims();
        let width = self.draw_width(v);
        let u = Tensor::<B, 2>::from_data(
            TensorData::new(uniforms(rng, m * width), [m, width]),
            &logits.device(),
        );
        self.draw_rows_with(logits, u, DeviceTopK::Rounds)
    }

    /// Uniform numbers per row that a draw over `v` ids takes (`min(top_k, v)`, or `v` without top-k).
    pub fn draw_width(&self, v: usize) -> usize {
        if self.top_k == 0 { v } else { self.top_k.min(v) }
    }

    /// [`Sampling::draw_rows`] with its uniform numbers in (0, 1) given, `[m, draw_width(v)]`, e.g. a
    /// slice of a block uploaded for many positions at once.
    pub fn draw_rows_with<B: Backend>(
        &self,
        logits: Tensor<B, 2>,
        u: Tensor<B, 2>,
        top: DeviceTopK,
    ) -> Tensor<B, 1, Int> {
        let [m, v] = logits.dims();
        let k = self.draw_width(v);
        // Most likely first where a filter needs the order; ids are positions in `ids` then.
        let (values, ids) = match (k < v, self.top_p < 1.0) {
            (true, _) => {
                let (x, i) = top.rows(logits, k);
                (x, Some(i))
            }
            // Sorts on the host (burn has no device sort): only top-p without top-k comes here.
            (false, true) => {
                let (x, i) = logits.sort_descending_with_indices(1);
                (x, Some(i))
            }
            (false, false) => (logits, None),
        };
        let width = values.dims()[1];
        let top = values.clone().max_dim(1);
        let mut scaled = (values - top).div_scalar(self.temperature);
        if self.top_p < 1.0 && self.top_p_rest && width > 1 {
            scaled = rest_nucleus(softmax(scaled, 1), self.top_p);
        } else if self.top_p < 1.0 {
            let probs = softmax(scaled.clone(), 1);
            // Keep an id while the more likely ones hold less than top_p (the first to reach it stays).
            let before = probs.clone().cumsum(1) - probs;
            scaled = scaled.mask_fill(before.greater_equal_elem(self.top_p), f32::NEG_INFINITY);
        }
        debug_assert_eq!(u.dims(), [m, width]);
        let gumbel = u.log().neg().log().neg();
        let pick = (scaled + gumbel).argmax(1);
        match ids {
            Some(ids) => ids.gather(1, pick).reshape([m]),
            None => pick.reshape([m]),
        }
    }
}

/// The log-weights of [`crate::sampling::nucleus`] with `rest` for rows of probabilities `[m, w]` (most
/// likely first, `w > 1`): the first column keeps its probability `p₀`; the others are kept while the
/// rest's mass before them is below `top_p · (1 − p₀)` and share `1 − p₀`. Cut ids are −∞.
fn rest_nucleus<B: Backend>(probs: Tensor<B, 2>, top_p: f64) -> Tensor<B, 2> {
    let [m, w] = probs.dims();
    let lead = probs.clone().slice([0..m, 0..1]);
    let share = lead.clone().neg().add_scalar(1.0);
    // The first column's "rest before it" is −p₀, below any threshold: it is never cut.
    let before = probs.clone().cumsum(1) - probs.clone() - lead.clone().expand([m, w]);
    let cut = before.greater_equal(share.clone().mul_scalar(top_p).expand([m, w]));
    let rest = probs.mask_fill(cut, 0.0).slice([0..m, 1..w]);
    // A row whose rest underflowed to 0 keeps zeros (0 × a large scale), not 0 / 0.
    let kept = rest.clone().sum_dim(1).clamp_min(f32::MIN_POSITIVE);
    let rest = rest * (share / kept).expand([m, w - 1]);
    Tensor::cat(vec![lead, rest], 1).log()
}

/// `n` uniform numbers in (0, 1), where both logarithms of the Gumbel noise stay finite.
pub fn uniforms(rng: &mut impl Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(f32::MIN_POSITIVE..1.0)).collect()
}

/// The `k` largest entries of each row of `x` `[m, v]` and their ids `[m, k]`, largest first, found on the
/// device: `k` rounds of argmax, gather and masking the id found. (burn's `topk_with_indices` sorts
/// every row on the host, a read-back and a sort of `m × v` values per decoded token.) Rows with fewer
/// than `k` finite entries repeat −∞ entries, which are never drawn.
fn top_k_rows<B: Backend>(x: Tensor<B, 2>, k: usize) -> (Tensor<B, 2>, Tensor<B, 2, Int>) {
    let [m, _] = x.dims();
    let hide = Tensor::<B, 2>::full([m, 1], f32::NEG_INFINITY, &x.device());
    let (mut values, mut ids) = (Vec::with_capacity(k), Vec::with_capacity(k));
    let mut rest = x;
    for _ in 0..k {
        let i = rest.clone().argmax(1);
        values.push(rest.clone().gather(1, i.clone()));
        rest = rest.scatter(1, i.clone(), hide.clone(), IndexingUpdateOp::Add);
        ids.push(i);
    }
    (Tensor::cat(values, 1), Tensor::cat(ids, 1))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use rand::{SeedableRng, rngs::StdRng};

    /// Counts of `draws` device draws from one row of logits (all rows in one batch).
    fn device_counts(s: Sampling, logits: &[f32], draws: usize) -> Vec<usize> {
        type F = burn::backend::Flex;
        let rows: Vec<f32> = (0..draws).flat_map(|_| logits.iter().copied()).collect();
        let t = Tensor::<F, 2>::from_data(TensorData::new(rows, [draws, logits.len()]), &Default::default());
        let mut c = vec![0; logits.len()];
        for id in s
            .draw_rows(t, &mut StdRng::seed_from_u64(3))
            .into_data()
            .iter::<i64>()
        {
            c[id as usize] += 1;
        }
        c
    }

    #[test]
    fn device_draws_follow_the_softmax_and_the_filters() {
        // As the host draw, with −∞ (masked) in place of NaN.
        crate::sampling::tests::check_draw_frequencies(device_counts, f32::NEG_INFINITY);
    }

    #[test]
    fn device_top_k_equals_a_host_sort() {
        type F = burn::backend::Flex;
        let mut rng = StdRng::seed_from_u64(9);
        let (m, v, k) = (5, 40, 7);
        let mut rows: Vec<f32> = (0..m * v).map(|_| rng.random_range(-3.0f32..3.0)).collect();
        // The last row has only 3 finite entries: the other 4 places hold −∞.
        for (j, x) in rows[(m - 1) * v..].iter_mut().enumerate() {
            if j % 13 != 0 {
                *x = f32::NEG_INFINITY;
            }
        }
        let t = Tensor::<F, 2>::from_data(TensorData::new(rows.clone(), [m, v]), &Default::default());
        let (values, ids) = top_k_rows(t, k);
        let values: Vec<f32> = values.into_data().iter::<f32>().collect();
        let ids: Vec<i64> = ids.into_data().iter::<i64>().collect();
        for r in 0..m {
            let row = &rows[r * v..(r + 1) * v];
            let mut order: Vec<usize> = (0..v).collect();
            order.sort_by(|&a, &b| row[b].total_cmp(&row[a]));
            for j in 0..k {
                let want = row[order[j]];
                assert_eq!(values[r * k + j], want, "row {r}, place {j}");
                if want.is_finite() {
                    assert_eq!(ids[r * k + j] as usize, order[j], "row {r}, place {j}");
                }
            }
        }
    }
}
