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
    /// Top-p cuts only the ids after the most likely one, which keeps its own probability: the nucleus
    /// is the top-p of the rest's mass, and the ids kept there share that mass. A plain nucleus of 0.8
    /// takes every departure away from an id above 0.8 (a standing agent never drives off); this one
    /// keeps departures at the model's rate and cuts only their tail. Nothing changes without top-p.
    #[serde(default)]
    pub top_p_rest: bool,
}

impl Default for Sampling {
    fn default() -> Self {
        Self {
            top_k: 16,
            top_p: 1.0,
            temperature: 1.0,
            top_p_rest: false,
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
            top_p_rest: false,
        }
    }

    /// One sampling per segment (`labels`, in frame order): `self`, with the top-k and top-p of the
    /// segments named in `top_k` and `top_p` replaced and [`top_p_rest`](Self::top_p_rest) set for those
    /// named in `top_p_rest` (the authors' evaluation draws ego, map and agents from their top 5, the
    /// image from its top 16). A name that is not a segment is refused, naming the segments there are.
    pub fn per_segment(
        self,
        top_k: &[(String, usize)],
        top_p: &[(String, f64)],
        top_p_rest: &[String],
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
        for name in top_p_rest {
            out[segment("top-p-rest", name)?].top_p_rest = true;
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
    /// cut to the top-p mass ([`nucleus`]).
    fn weighted(&self, logits: &[f32], mut order: Vec<usize>) -> Vec<(u32, f64)> {
        let top = f64::from(logits[order[0]]);
        let mut probs: Vec<f64> = order
            .iter()
            .map(|&i| ((f64::from(logits[i]) - top) / self.temperature).exp())
            .collect();
        let total: f64 = probs.iter().sum();
        probs.iter_mut().for_each(|p| *p /= total);
        if self.top_p < 1.0 {
            let keep = nucleus(&mut probs, self.top_p, self.top_p_rest);
            order.truncate(keep);
        }
        order.into_iter().map(|i| i as u32).zip(probs).collect()
    }
}

/// Cuts `probs` (a distribution, most likely first) to its top-p nucleus and rescales what is kept;
/// returns how many are kept. The ids kept are the most likely ones until their mass reaches `top_p`
/// (the first to reach it stays); with `rest`, the first id keeps its probability and the cut is made
/// among the others, against `top_p` of their mass `1 − probs[0]`, which the kept ones then share. The
/// engine's draws (`draw.cu`, `host_draw.rs`) do the same arithmetic in the same order.
pub fn nucleus(probs: &mut Vec<f64>, top_p: f64, rest: bool) -> usize {
    let skip = usize::from(rest && !probs.is_empty());
    let share = if skip == 1 { 1.0 - probs[0] } else { 1.0 };
    let mut mass = 0.0;
    let keep = probs[skip..]
        .iter()
        .position(|p| {
            mass += p;
            mass >= top_p * share
        })
        .map_or(probs.len(), |i| skip + i + 1);
    probs.truncate(keep);
    let kept: f64 = probs[skip..].iter().sum();
    if kept > 0.0 {
        probs[skip..].iter_mut().for_each(|p| *p = *p / kept * share);
    }
    keep
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
#[path = "sampling_tests.rs"]
pub(crate) mod tests;
