//! Per-modality statistics of a dataset: exact, and mergeable across logs.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Count, range, mean and spread of one quantity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Values seen.
    pub count: u64,
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
    /// Sum of values.
    pub sum: f64,
    /// Sum of squared values.
    pub sum_sq: f64,
}

impl Default for Summary {
    fn default() -> Self {
        Self {
            count: 0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            sum: 0.0,
            sum_sq: 0.0,
        }
    }
}

impl Summary {
    /// Adds a value.
    pub fn add(&mut self, v: f64) {
        self.count += 1;
        self.min = self.min.min(v);
        self.max = self.max.max(v);
        self.sum += v;
        self.sum_sq += v * v;
    }

    /// Adds another summary.
    pub fn merge(&mut self, o: &Summary) {
        self.count += o.count;
        self.min = self.min.min(o.min);
        self.max = self.max.max(o.max);
        self.sum += o.sum;
        self.sum_sq += o.sum_sq;
    }

    /// Mean (0 when empty).
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum / self.count as f64
        }
    }

    /// Standard deviation (0 when empty).
    pub fn std(&self) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let m = self.mean();
        (self.sum_sq / self.count as f64 - m * m).max(0.0).sqrt()
    }
}

/// Statistics per modality: `ego` (dx, dy, dtheta, speed) and `agent` (positions, velocities, headings,
/// sizes, agents per frame, categories).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Frames seen.
    pub frames: u64,
    /// Ego quantities.
    pub ego: BTreeMap<String, Summary>,
    /// Agent quantities.
    pub agent: BTreeMap<String, Summary>,
    /// Agents seen per category name.
    pub categories: BTreeMap<String, u64>,
}

impl Stats {
    /// Adds a value to a named ego quantity.
    pub fn ego(&mut self, key: &str, v: f64) {
        self.ego.entry(key.into()).or_default().add(v);
    }

    /// Adds a value to a named agent quantity.
    pub fn agent(&mut self, key: &str, v: f64) {
        self.agent.entry(key.into()).or_default().add(v);
    }

    /// Adds other statistics.
    pub fn merge(&mut self, o: &Stats) {
        self.frames += o.frames;
        for (k, v) in &o.ego {
            self.ego.entry(k.clone()).or_default().merge(v);
        }
        for (k, v) in &o.agent {
            self.agent.entry(k.clone()).or_default().merge(v);
        }
        for (k, v) in &o.categories {
            *self.categories.entry(k.clone()).or_default() += v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summaries_merge_exactly() {
        let (mut a, mut b, mut all) = (Summary::default(), Summary::default(), Summary::default());
        for v in [1.0, 2.0, 6.0] {
            a.add(v);
            all.add(v);
        }
        for v in [-3.0, 4.0] {
            b.add(v);
            all.add(v);
        }
        a.merge(&b);
        assert_eq!(a, all);
        assert_eq!((a.min, a.max, a.count), (-3.0, 6.0, 5));
        assert!((a.mean() - 2.0).abs() < 1e-12);
        let var = [1.0f64, 2.0, 6.0, -3.0, 4.0]
            .iter()
            .map(|v| (v - 2.0).powi(2))
            .sum::<f64>()
            / 5.0;
        assert!((a.std() - var.sqrt()).abs() < 1e-12);
    }
}
