//! Control files: what the user imposes on a rollout (`docs/control.md`).

use crate::error::{GenerateError, Result};
use serde::Deserialize;

/// A constant ego motion for a range of generated frames.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EgoControl {
    /// First generated frame it applies to (0 = the first new frame).
    pub from: usize,
    /// One past the last (exclusive).
    pub to: usize,
    /// Forward motion per frame (m).
    pub dx: f64,
    /// Leftward motion per frame (m).
    #[serde(default)]
    pub dy: f64,
    /// Heading change per frame (rad; positive turns left).
    #[serde(default)]
    pub dtheta: f64,
}

/// A control file: `[[ego]]` entries (TOML), or `{"ego": [...]}` (JSON).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Control {
    /// Forced ego motions.
    #[serde(default)]
    pub ego: Vec<EgoControl>,
}

impl Control {
    /// Refuses empty or overlapping ranges, naming the entry.
    pub fn validate(&self) -> Result<()> {
        for (i, e) in self.ego.iter().enumerate() {
            if e.from >= e.to {
                return Err(GenerateError::Settings(format!(
                    "ego[{i}]: from {} is not below to {}",
                    e.from, e.to
                )));
            }
            if let Some(j) = self.ego[..i].iter().position(|o| o.from < e.to && e.from < o.to) {
                return Err(GenerateError::Settings(format!("ego[{i}] overlaps ego[{j}]")));
            }
            if ![e.dx, e.dy, e.dtheta].iter().all(|v| v.is_finite()) {
                return Err(GenerateError::Settings(format!(
                    "ego[{i}]: values must be finite"
                )));
            }
        }
        Ok(())
    }

    /// The action tokens forced at generated frame `k`, given the action bins `(lo, hi, bins)` of dx, dy,
    /// dθ; values outside a range take its first or last bin (counted in the returned number).
    pub fn action_at(&self, k: usize, bins: &[(f64, f64, u32); 3]) -> Option<(Vec<u32>, usize)> {
        let e = self.ego.iter().find(|e| e.from <= k && k < e.to)?;
        let mut clamped = 0;
        let ids = [e.dx, e.dy, e.dtheta]
            .iter()
            .zip(bins)
            .map(|(v, (lo, hi, n))| {
                let x = ((v - lo) / (hi - lo) * f64::from(*n)).floor();
                if x < 0.0 || x >= f64::from(*n) {
                    clamped += 1;
                }
                x.clamp(0.0, f64::from(n - 1)) as u32
            })
            .collect();
        Some((ids, clamped))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn ranges_bins_and_errors() {
        let c = Control {
            ego: vec![
                EgoControl {
                    from: 0,
                    to: 5,
                    dx: 2.0,
                    dy: 0.0,
                    dtheta: 0.1,
                },
                EgoControl {
                    from: 5,
                    to: 6,
                    dx: 99.0,
                    dy: 0.0,
                    dtheta: 0.0,
                },
            ],
        };
        c.validate().unwrap();
        let bins = [(0.0, 8.0, 16), (-1.0, 1.0, 16), (-0.5, 0.5, 16)];
        // dx 2.0 → bin 4 of 0.5 m; dy 0 → bin 8; dθ 0.1 → bin 9 of 1/16 rad.
        assert_eq!(c.action_at(3, &bins), Some((vec![4, 8, 9], 0)));
        assert_eq!(c.action_at(5, &bins), Some((vec![15, 8, 8], 1)));
        assert_eq!(c.action_at(6, &bins), None);
        let bad = Control {
            ego: vec![
                c.ego[0].clone(),
                EgoControl {
                    from: 4,
                    to: 9,
                    ..c.ego[1].clone()
                },
            ],
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("ego[1] overlaps ego[0]")
        );
    }
}
