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

    /// One sampling per segment (`labels`, in frame order): `self`, with the top-k and top-p of the
    /// segments named in `top_k` and `top_p` replaced (the authors' evaluation draws ego, map and agents
    /// from their top 5, the image from its top 16). A name that is not a segment is refused, naming the
    /// segments there are.
    pub fn per_segment(
        self,
        top_k: &[(String, usize)],
        top_p: &[(String, f64)],
        labels: &[&str],
    ) -> Result<Vec<Self>> {
        let segment = |what: &str, name: &str| {
            labels.iter().position(|l| *l == name).ok_or_else(|| {
                GenerateError::Settings(format!(
                    "{what} for `{name}`: this model has no such modality (it has {})",
                    labels.join(", ")
                ))
            })
        };
        let mut out = vec![self; labels.len()];
        for (name, k) in top_k {
            out[segment("top-k", name)?].top_k = *k;
        }
        for (name, p) in top_p {
            out[segment("top-p", name)?].top_p = *p;
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
        walk(&self.distribution(logits), rng)
    }

    /// Draws the first id of a token group (an agent slot: an agent or `pad`) from `logits`, from
    /// [`distribution_present`](Self::distribution_present).
    pub fn draw_present(&self, logits: &[f32], pad: u32, rng: &mut impl Rng) -> u32 {
        walk(&self.distribution_present(logits, pad), rng)
    }

    /// The distribution of a token group's first id (an agent slot: a value, or `pad` for no agent):
    /// `pad` keeps its untruncated share of the tempered softmax over every finite logit, and the values
    /// among the top-k ids (top-p among them) share the rest. A top-k list alone would give pad nearly all
    /// of an empty slot's mass (an entering agent's is spread over many position bins) and so almost never
    /// let an agent enter. With top-k 1 (greedy) or 0 (no truncation) it is [`distribution`](Self::distribution).
    pub fn distribution_present(&self, logits: &[f32], pad: u32) -> Vec<(u32, f64)> {
        if self.top_k <= 1 {
            return self.distribution(logits);
        }
        let finite = || logits.iter().filter(|x| x.is_finite()).map(|&x| f64::from(x));
        let Some(top) = finite().reduce(f64::max) else {
            return Vec::new();
        };
        let e = |x: f64| ((x - top) / self.temperature).exp();
        let total: f64 = finite().map(e).sum();
        let share = logits
            .get(pad as usize)
            .filter(|x| x.is_finite())
            .map_or(0.0, |&x| e(f64::from(x)) / total);
        let mut order = self.ranked(logits);
        order.retain(|&i| i != pad as usize);
        if order.is_empty() {
            return vec![(pad, 1.0)];
        }
        let mut out = vec![(pad, share)];
        out.extend(
            self.weighted(logits, order)
                .into_iter()
                .map(|(i, p)| (i, p * (1.0 - share))),
        );
        out
    }

    /// The distribution [`draw`](Self::draw) draws from: ids with their probabilities, most likely first
    /// (empty when no logit is finite).
    pub fn distribution(&self, logits: &[f32]) -> Vec<(u32, f64)> {
        let order = self.ranked(logits);
        if order.is_empty() {
            return Vec::new();
        }
        self.weighted(logits, order)
    }

    /// The ids a draw considers: the finite ones, the top k of them, most likely first (ties by id).
    fn ranked(&self, logits: &[f32]) -> Vec<usize> {
        // Non-finite logits (NaN, masked −∞) are never drawn.
        let mut order: Vec<usize> = (0..logits.len()).filter(|&i| logits[i].is_finite()).collect();
        if order.is_empty() {
            return order;
        }
        // Most likely first, ties by id: one total order, so the draw does not depend on how it is sorted.
        let most_likely = |a: &usize, b: &usize| logits[*b].total_cmp(&logits[*a]).then(a.cmp(b));
        if self.top_k > 0 && self.top_k < order.len() {
            // Selecting the k best is linear; sorting all 8,192 ids for 16 of them was most of a draw.
            order.select_nth_unstable_by(self.top_k - 1, most_likely);
            order.truncate(self.top_k);
        }
        order.sort_unstable_by(most_likely);
        order
    }

    /// `order` (non-empty, most likely first) with the probabilities of the tempered softmax over it,
    /// cut to the top-p mass.
    fn weighted(&self, logits: &[f32], mut order: Vec<usize>) -> Vec<(u32, f64)> {
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
/// One uniform number walked along `dist` (the last id where rounding leaves some over; 0 when empty).
fn walk(dist: &[(u32, f64)], rng: &mut impl Rng) -> u32 {
    let Some(&(last, _)) = dist.last() else {
        return 0;
    };
    let mut u: f64 = rng.random();
    for &(i, p) in dist {
        if u < p {
            return i;
        }
        u -= p;
    }
    last
}

#[cfg(test)]
pub(crate) mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use rand::{SeedableRng, rngs::StdRng};

    #[test]
    fn per_segment_settings_replace_named_segments_and_refuse_unknown_ones() {
        let labels = ["ego", "map", "agent", "image"];
        let base = Sampling::default();
        let got = base
            .per_segment(
                &[("map".into(), 5), ("agent".into(), 64)],
                &[("agent".into(), 0.8)],
                &labels,
            )
            .unwrap();
        let ks: Vec<usize> = got.iter().map(|s| s.top_k).collect();
        assert_eq!(ks, [16, 5, 64, 16]);
        let ps: Vec<f64> = got.iter().map(|s| s.top_p).collect();
        assert_eq!(ps, [1.0, 1.0, 0.8, 1.0]);
        assert!(got.iter().all(|s| s.temperature == base.temperature));
        for (k, p, what) in [
            (vec![("lidar".to_string(), 5)], vec![], "top-k for `lidar`"),
            (vec![], vec![("lidar".to_string(), 0.5)], "top-p for `lidar`"),
        ] {
            let e = base.per_segment(&k, &p, &labels).unwrap_err().to_string();
            assert!(e.contains(what) && e.contains("ego, map, agent, image"), "{e}");
        }
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
    fn a_group_first_draw_keeps_pad_at_its_untruncated_share() {
        // 200 equal values and pad at 9 × their mass: pad's share of the softmax is 0.9, of a top-5 list
        // (pad and four values) 1800 / 1804.
        let pad = 290u32;
        let mut logits = vec![f32::NEG_INFINITY; 300];
        logits[..200].iter_mut().for_each(|x| *x = 0.0);
        logits[pad as usize] = (9.0f32 * 200.0).ln();
        let s = Sampling {
            top_k: 5,
            top_p: 1.0,
            temperature: 1.0,
        };
        let d = s.distribution_present(&logits, pad);
        assert_eq!(d[0].0, pad);
        // (The pad logit is ln 1800 in f32.)
        assert!((d[0].1 - 0.9).abs() < 1e-6, "{d:?}");
        // The list's four values (ties to the smaller ids) share the rest equally.
        let values: Vec<u32> = d[1..].iter().map(|(i, _)| *i).collect();
        assert_eq!(values, [0, 1, 2, 3]);
        assert!(d[1..].iter().all(|(_, p)| (p - 0.025).abs() < 1e-6), "{d:?}");
        let plain = s.distribution(&logits);
        assert!((plain[0].1 - 1800.0 / 1804.0).abs() < 1e-6, "{plain:?}");
        // Draws follow it.
        let mut rng = StdRng::seed_from_u64(3);
        let n = 20_000;
        let pads = (0..n)
            .filter(|_| s.draw_present(&logits, pad, &mut rng) == pad)
            .count();
        assert!((pads as f64 / n as f64 - 0.9).abs() < 0.01, "{pads}");
        // Greedy and untruncated draws are the plain ones; a masked pad has no share; no values: pad.
        for k in [0, 1] {
            let t = Sampling { top_k: k, ..s };
            assert_eq!(t.distribution_present(&logits, pad), t.distribution(&logits));
        }
        let mut no_pad = logits.clone();
        no_pad[pad as usize] = f32::NEG_INFINITY;
        let d = s.distribution_present(&no_pad, pad);
        assert_eq!(d[0], (pad, 0.0));
        assert!((d[1..].iter().map(|(_, p)| p).sum::<f64>() - 1.0).abs() < 1e-12);
        let mut only_pad = vec![f32::NEG_INFINITY; 300];
        only_pad[pad as usize] = 0.0;
        assert_eq!(s.distribution_present(&only_pad, pad), [(pad, 1.0)]);
        // With top-p, the values are cut among themselves: 0.5 of their mass keeps two of the four.
        let t = Sampling { top_p: 0.5, ..s };
        let d = t.distribution_present(&logits, pad);
        assert_eq!(d.len(), 3, "{d:?}");
        assert!((d[1].1 - 0.05).abs() < 1e-6, "{d:?}");
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
