//! Drawing a token from logits: temperature, top-k and top-p (nucleus), seeded.

use crate::error::{GenerateError, Result};
use burn::tensor::activation::softmax;
use burn::tensor::backend::Backend;
use burn::tensor::{IndexingUpdateOp, Int, Tensor, TensorData};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// How one modality's tokens are drawn. Defaults are the paper's: top-k 16, temperature 1.0, no nucleus.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Sampling {
    /// Keep the k most likely ids (0 = all).
    pub top_k: usize,
    /// Keep the smallest set of most likely ids whose probability reaches p (1.0 = all).
    pub top_p: f64,
    /// Divide the logits by this before the softmax (> 0; smaller is greedier).
    pub temperature: f64,
}

impl Default for Sampling {
    fn default() -> Self {
        Self {
            top_k: 16,
            top_p: 1.0,
            temperature: 1.0,
        }
    }
}

impl Sampling {
    /// Always the most likely id.
    pub fn greedy() -> Self {
        Self {
            top_k: 1,
            top_p: 1.0,
            temperature: 1.0,
        }
    }

    /// One sampling per segment (`labels`, in frame order): `self`, with the top-k of the segments named in
    /// `top_k` replaced (the authors' evaluation draws ego, map and agents from their top 5, the image
    /// from its top 16). A name that is not a segment is refused, naming the segments there are.
    pub fn per_segment(self, top_k: &[(String, usize)], labels: &[&str]) -> Result<Vec<Self>> {
        let mut out = vec![self; labels.len()];
        for (name, k) in top_k {
            let i = labels.iter().position(|l| l == name).ok_or_else(|| {
                GenerateError::Settings(format!(
                    "top-k for `{name}`: this model has no such modality (it has {})",
                    labels.join(", ")
                ))
            })?;
            out[i].top_k = *k;
        }
        Ok(out)
    }

    /// Refuses settings that cannot sample; `what` names them in the error (e.g. `sampling.map`).
    pub fn validate(&self, what: &str) -> Result<()> {
        if !(self.temperature > 0.0 && self.temperature.is_finite()) {
            return Err(GenerateError::Settings(format!(
                "{what}.temperature = {}: must be a positive number",
                self.temperature
            )));
        }
        if !(self.top_p > 0.0 && self.top_p <= 1.0) {
            return Err(GenerateError::Settings(format!(
                "{what}.top_p = {}: must be in (0, 1]",
                self.top_p
            )));
        }
        Ok(())
    }

    /// Draws an id from `logits` (one row).
    pub fn draw(&self, logits: &[f32], rng: &mut impl Rng) -> u32 {
        // Non-finite logits (NaN, masked −∞) are never drawn.
        let mut order: Vec<usize> = (0..logits.len()).filter(|&i| logits[i].is_finite()).collect();
        if order.is_empty() {
            return 0;
        }
        // Most likely first, ties by id: one total order, so the draw does not depend on how it is sorted.
        let most_likely = |a: &usize, b: &usize| logits[*b].total_cmp(&logits[*a]).then(a.cmp(b));
        if self.top_k > 0 && self.top_k < order.len() {
            // Selecting the k best is linear; sorting all 8,192 ids for 16 of them was most of a draw.
            order.select_nth_unstable_by(self.top_k - 1, most_likely);
            order.truncate(self.top_k);
        }
        order.sort_unstable_by(most_likely);
        let top = f64::from(logits[order[0]]);
        let mut probs: Vec<f64> = order
            .iter()
            .map(|&i| ((f64::from(logits[i]) - top) / self.temperature).exp())
            .collect();
        let total: f64 = probs.iter().sum();
        probs.iter_mut().for_each(|p| *p /= total);
        if self.top_p < 1.0 {
            let mut mass = 0.0;
            let keep = probs
                .iter()
                .position(|p| {
                    mass += p;
                    mass >= self.top_p
                })
                .map_or(probs.len(), |i| i + 1);
            probs.truncate(keep);
            order.truncate(keep);
            let total: f64 = probs.iter().sum();
            probs.iter_mut().for_each(|p| *p /= total);
        }
        let mut u: f64 = rng.random();
        for (p, &i) in probs.iter().zip(&order) {
            if u < *p {
                return i as u32;
            }
            u -= p;
        }
        order[order.len() - 1] as u32
    }

    /// One draw per row of `logits` (`[m, v]`) on their device, with the distribution of [`Self::draw`]
    /// (top-k, temperature, top-p; −∞ is never drawn; rows must hold no NaN). Nothing is read back to
    /// the host, so the ids can feed the next decoding step directly. Gumbel-max: the argmax of the
    /// filtered, tempered logits plus Gumbel noise is a draw from their softmax. The uniform numbers come
    /// from `rng` and are uploaded (`m × min(top_k, v)` of them), not from the backend's generator, which
    /// is one per process: draws stay a function of the seed whatever else runs.
    pub fn draw_rows<B: Backend>(&self, logits: Tensor<B, 2>, rng: &mut impl Rng) -> Tensor<B, 1, Int> {
        let [m, v] = logits.dims();
        let device = logits.device();
        let k = if self.top_k == 0 { v } else { self.top_k.min(v) };
        // Most likely first where a filter needs the order; ids are positions in `ids` then.
        let (values, ids) = match (k < v, self.top_p < 1.0) {
            (true, _) => {
                let (x, i) = top_k_rows(logits, k);
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
        if self.top_p < 1.0 {
            let probs = softmax(scaled.clone(), 1);
            // Keep an id while the more likely ones hold less than top_p (the first to reach it stays).
            let before = probs.clone().cumsum(1) - probs;
            scaled = scaled.mask_fill(before.greater_equal_elem(self.top_p), f32::NEG_INFINITY);
        }
        // u in (0, 1): both logarithms stay finite.
        let u: Vec<f32> = (0..m * width)
            .map(|_| rng.random_range(f32::MIN_POSITIVE..1.0))
            .collect();
        let u = Tensor::<B, 2>::from_data(TensorData::new(u, [m, width]), &device);
        let gumbel = u.log().neg().log().neg();
        let pick = (scaled + gumbel).argmax(1);
        match ids {
            Some(ids) => ids.gather(1, pick).reshape([m]),
            None => pick.reshape([m]),
        }
    }
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

    #[test]
    fn per_segment_top_k_replaces_named_segments_and_refuses_unknown_ones() {
        let labels = ["ego", "map", "agent", "image"];
        let base = Sampling::default();
        let got = base
            .per_segment(&[("map".into(), 5), ("agent".into(), 5)], &labels)
            .unwrap();
        let ks: Vec<usize> = got.iter().map(|s| s.top_k).collect();
        assert_eq!(ks, [16, 5, 5, 16]);
        assert!(
            got.iter()
                .all(|s| s.temperature == base.temperature && s.top_p == base.top_p)
        );
        let e = base
            .per_segment(&[("lidar".into(), 5)], &labels)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`lidar`") && e.contains("ego, map, agent, image"),
            "{e}"
        );
    }

    fn counts(s: Sampling, logits: &[f32], draws: usize) -> Vec<usize> {
        let mut rng = StdRng::seed_from_u64(1);
        let mut c = vec![0; logits.len()];
        for _ in 0..draws {
            c[s.draw(logits, &mut rng) as usize] += 1;
        }
        c
    }

    #[test]
    fn frequencies_follow_the_softmax_and_the_filters() {
        let logits = [0.0f32, (2.0f32).ln(), (3.0f32).ln(), f32::NAN, (4.0f32).ln()];
        let all = Sampling {
            top_k: 0,
            top_p: 1.0,
            temperature: 1.0,
        };
        let c = counts(all, &logits, 100_000);
        // Probabilities 1:2:3:4 over the finite logits.
        for (i, want) in [(0, 0.1), (1, 0.2), (2, 0.3), (4, 0.4)] {
            let got = c[i] as f64 / 100_000.0;
            assert!((got - want).abs() < 0.01, "id {i}: {got} vs {want}");
        }
        assert_eq!(c[3], 0, "NaN never drawn");
        // top-k 2 keeps ids 4 and 2 (4:3).
        let c = counts(Sampling { top_k: 2, ..all }, &logits, 50_000);
        assert_eq!(c[0] + c[1], 0);
        assert!((c[4] as f64 / 50_000.0 - 4.0 / 7.0).abs() < 0.01);
        // top-p 0.5: 0.4 alone is not enough, 0.4 + 0.3 is: ids 4 and 2.
        let c = counts(Sampling { top_p: 0.5, ..all }, &logits, 20_000);
        assert_eq!(c[0] + c[1], 0);
        assert!(c[2] > 0 && c[4] > 0);
        // A low temperature is nearly greedy; greedy is exactly.
        let c = counts(
            Sampling {
                temperature: 0.05,
                ..all
            },
            &logits,
            2_000,
        );
        assert!(c[4] > 1_990);
        assert_eq!(counts(Sampling::greedy(), &logits, 100)[4], 100);
    }

    /// The draw as first written: sort every id, then cut to the top k.
    fn draw_by_full_sort(s: &Sampling, logits: &[f32], rng: &mut impl Rng) -> u32 {
        let mut order: Vec<usize> = (0..logits.len()).collect();
        order.sort_by(|&a, &b| logits[b].total_cmp(&logits[a]).then(a.cmp(&b)));
        order.retain(|&i| logits[i].is_finite());
        order.truncate(s.top_k);
        let top = f64::from(logits[order[0]]);
        let probs: Vec<f64> = order
            .iter()
            .map(|&i| ((f64::from(logits[i]) - top) / s.temperature).exp())
            .collect();
        let total: f64 = probs.iter().sum();
        let mut u: f64 = rng.random();
        for (p, &i) in probs.iter().zip(&order) {
            if u < *p / total {
                return i as u32;
            }
            u -= *p / total;
        }
        order[order.len() - 1] as u32
    }

    #[test]
    fn selecting_the_top_k_draws_what_sorting_everything_drew() {
        let mut data = StdRng::seed_from_u64(5);
        for k in [1, 2, 16, 100] {
            let s = Sampling {
                top_k: k,
                ..Default::default()
            };
            let (mut a, mut b) = (StdRng::seed_from_u64(9), StdRng::seed_from_u64(9));
            for _ in 0..200 {
                // Few distinct values, so ties are common; some ids masked.
                let logits: Vec<f32> = (0..500)
                    .map(|_| match data.random_range(0..10) {
                        0 => f32::NEG_INFINITY,
                        v => v as f32 * 0.5,
                    })
                    .collect();
                assert_eq!(s.draw(&logits, &mut a), draw_by_full_sort(&s, &logits, &mut b));
            }
        }
    }

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
        // As the host test, with −∞ (masked) in place of NaN.
        let logits = [
            0.0f32,
            (2.0f32).ln(),
            (3.0f32).ln(),
            f32::NEG_INFINITY,
            (4.0f32).ln(),
        ];
        let all = Sampling {
            top_k: 0,
            top_p: 1.0,
            temperature: 1.0,
        };
        let c = device_counts(all, &logits, 100_000);
        for (i, want) in [(0, 0.1), (1, 0.2), (2, 0.3), (4, 0.4)] {
            let got = c[i] as f64 / 100_000.0;
            assert!((got - want).abs() < 0.01, "id {i}: {got} vs {want}");
        }
        assert_eq!(c[3], 0, "masked ids are never drawn");
        let c = device_counts(Sampling { top_k: 2, ..all }, &logits, 50_000);
        assert_eq!(c[0] + c[1] + c[3], 0);
        assert!((c[4] as f64 / 50_000.0 - 4.0 / 7.0).abs() < 0.01, "{c:?}");
        // top-p 0.5 keeps ids 4 and 2, renormalised 4:3; top-p 0.3 keeps id 4 alone.
        let c = device_counts(Sampling { top_p: 0.5, ..all }, &logits, 50_000);
        assert_eq!(c[0] + c[1] + c[3], 0);
        assert!((c[4] as f64 / 50_000.0 - 4.0 / 7.0).abs() < 0.01, "{c:?}");
        assert_eq!(
            device_counts(Sampling { top_p: 0.3, ..all }, &logits, 1_000)[4],
            1_000
        );
        // Temperature 0.5 squares the odds: 1:4:9:16.
        let c = device_counts(
            Sampling {
                temperature: 0.5,
                ..all
            },
            &logits,
            100_000,
        );
        assert!((c[4] as f64 / 100_000.0 - 16.0 / 30.0).abs() < 0.01, "{c:?}");
        assert_eq!(device_counts(Sampling::greedy(), &logits, 100)[4], 100);
        // top-k and top-p together: top-k 3 keeps 4, 2, 1; top-p 0.5 of those (4/9, 3/9, 2/9) keeps 4, 2.
        let c = device_counts(
            Sampling {
                top_k: 3,
                top_p: 0.5,
                ..all
            },
            &logits,
            50_000,
        );
        assert_eq!(c[0] + c[1] + c[3], 0, "{c:?}");
        assert!((c[4] as f64 / 50_000.0 - 4.0 / 7.0).abs() < 0.01, "{c:?}");
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

    #[test]
    fn bad_settings_are_named() {
        let e = Sampling {
            temperature: 0.0,
            ..Default::default()
        }
        .validate("sampling.map")
        .unwrap_err();
        assert!(e.to_string().contains("sampling.map.temperature = 0"), "{e}");
        let e = Sampling {
            top_p: 1.5,
            ..Default::default()
        }
        .validate("sampling.agent")
        .unwrap_err();
        assert!(e.to_string().contains("sampling.agent.top_p = 1.5"), "{e}");
    }
}
