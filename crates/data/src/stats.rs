//! Per-modality statistics of a dataset: exact, and mergeable across logs.

use crate::error::Result;
use crate::index::ClipEntry;
use crate::log::Log;
use crate::view::{ViewOptions, frames};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

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

/// Statistics over every frame of the clips, cut exactly as readers will cut them.
pub(crate) fn clip_stats(log: &Log, clips: &[ClipEntry], view: &ViewOptions, path: &Path) -> Result<Stats> {
    let mut st = Stats::default();
    for c in clips {
        let steps: Vec<&[_]> = log.steps[c.first_step..c.first_step + c.frames]
            .iter()
            .map(Vec::as_slice)
            .collect();
        let before = c.first_step.checked_sub(1).and_then(|s| {
            let step = &log.steps[s];
            step.binary_search_by_key(&c.ego_track, |x| x.track)
                .ok()
                .map(|i| step[i])
        });
        for f in frames(
            path,
            &log.tracks,
            c.ego_track,
            &steps,
            before.as_ref(),
            log.dt,
            view,
        )? {
            st.frames += 1;
            st.ego("dx", f.action.dx);
            st.ego("dy", f.action.dy);
            st.ego("dtheta", f.action.dtheta);
            st.ego("speed", f.ego.speed);
            st.agent("per_frame", f.agents.len() as f64);
            for a in &f.agents {
                *st.categories.entry(a.category.name().into()).or_default() += 1;
                for (k, v) in [
                    ("x", a.x),
                    ("y", a.y),
                    ("vx", a.vx),
                    ("vy", a.vy),
                    ("heading", a.heading),
                    ("length", a.length),
                    ("width", a.width),
                    ("height", a.height),
                ] {
                    st.agent(k, v);
                }
            }
        }
    }
    Ok(st)
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
