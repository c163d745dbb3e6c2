//! Drawing a token from logits: temperature, top-k and top-p (nucleus), seeded.

use crate::error::{GenerateError, Result};
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
        let dist = self.distribution(logits);
        let Some(&(last, _)) = dist.last() else {
            return 0;
        };
        let mut u: f64 = rng.random();
        for &(i, p) in &dist {
            if u < p {
                return i;
            }
            u -= p;
        }
        last
    }

    /// The distribution [`draw`](Self::draw) draws from: ids with their probabilities, most likely first
    /// (empty when no logit is finite).
    pub fn distribution(&self, logits: &[f32]) -> Vec<(u32, f64)> {
        // Non-finite logits (NaN, masked −∞) are never drawn.
        let mut order: Vec<usize> = (0..logits.len()).filter(|&i| logits[i].is_finite()).collect();
        if order.is_empty() {
            return Vec::new();
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
        order.into_iter().map(|i| i as u32).zip(probs).collect()
    }
}
#[cfg(test)]
pub(crate) mod tests {
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

    /// Checks a way of drawing (`count(s, logits, n)`: how often each id came out of `n` draws) against
    /// the softmax of logits 0, ln 2, ln 3, `masked`, ln 4 under each filter: probabilities 1:2:3:4, the
    /// masked id never.
    pub(crate) fn check_draw_frequencies(count: impl Fn(Sampling, &[f32], usize) -> Vec<usize>, masked: f32) {
        let logits = [0.0f32, (2.0f32).ln(), (3.0f32).ln(), masked, (4.0f32).ln()];
        let all = Sampling {
            top_k: 0,
            top_p: 1.0,
            temperature: 1.0,
        };
        let share = |c: &[usize], i: usize, n: usize| c[i] as f64 / n as f64;
        let c = count(all, &logits, 100_000);
        for (i, want) in [(0, 0.1), (1, 0.2), (2, 0.3), (4, 0.4)] {
            let got = share(&c, i, 100_000);
            assert!((got - want).abs() < 0.01, "id {i}: {got} vs {want}");
        }
        assert_eq!(c[3], 0, "the masked id is never drawn");
        // top-k 2 keeps ids 4 and 2 (4:3); top-p 0.5 too (0.4 alone is not enough, 0.4 + 0.3 is);
        // top-p 0.3 keeps id 4 alone; top-k 3 keeps 4, 2, 1 and top-p 0.5 of those (4/9, 3/9) 4 and 2.
        for s in [
            Sampling { top_k: 2, ..all },
            Sampling { top_p: 0.5, ..all },
            Sampling {
                top_k: 3,
                top_p: 0.5,
                ..all
            },
        ] {
            let c = count(s, &logits, 50_000);
            assert_eq!(c[0] + c[1] + c[3], 0, "{s:?}: {c:?}");
            assert!((share(&c, 4, 50_000) - 4.0 / 7.0).abs() < 0.01, "{s:?}: {c:?}");
        }
        assert_eq!(count(Sampling { top_p: 0.3, ..all }, &logits, 1_000)[4], 1_000);
        // Temperature 0.5 squares the odds (1:4:9:16); greedy is always the most likely id.
        let c = count(
            Sampling {
                temperature: 0.5,
                ..all
            },
            &logits,
            100_000,
        );
        assert!((share(&c, 4, 100_000) - 16.0 / 30.0).abs() < 0.01, "{c:?}");
        assert_eq!(count(Sampling::greedy(), &logits, 100)[4], 100);
    }

    #[test]
    fn frequencies_follow_the_softmax_and_the_filters() {
        check_draw_frequencies(counts, f32::NAN);
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
