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

/// An agent's state set for a range of generated frames: the agent in slot `slot` (a generated agent's
/// `track_id`) gets the given values, in the ego frame of each generated frame; values left out are
/// generated.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentControl {
    /// Agent slot.
    pub slot: usize,
    /// First generated frame it applies to.
    pub from: usize,
    /// One past the last (exclusive).
    pub to: usize,
    /// Position ahead of the ego (m).
    pub x: Option<f64>,
    /// Position to the left of the ego (m).
    pub y: Option<f64>,
    /// Velocity ahead (m/s).
    pub vx: Option<f64>,
    /// Velocity to the left (m/s).
    pub vy: Option<f64>,
    /// Heading relative to the ego (rad).
    pub heading: Option<f64>,
    /// `vehicle` (default), `pedestrian` or `cyclist`: placed with the values, so that an empty slot
    /// becomes an agent.
    pub category: Option<String>,
}

impl AgentControl {
    /// The set values as (field name, value), in the agent modality's field order.
    pub fn values(&self) -> Vec<(&'static str, f64)> {
        [
            ("x", self.x),
            ("y", self.y),
            ("vx", self.vx),
            ("vy", self.vy),
            ("heading", self.heading),
        ]
        .into_iter()
        .filter_map(|(k, v)| v.map(|v| (k, v)))
        .collect()
    }
}

/// A control file: `[[ego]]` and `[[agent]]` entries (TOML), or `{"ego": [...], "agent": [...]}` (JSON).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Control {
    /// Forced ego motions.
    #[serde(default)]
    pub ego: Vec<EgoControl>,
    /// Agent states.
    #[serde(default)]
    pub agent: Vec<AgentControl>,
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
        for (i, a) in self.agent.iter().enumerate() {
            if a.from >= a.to {
                return Err(GenerateError::Settings(format!(
                    "agent[{i}]: from {} is not below to {}",
                    a.from, a.to
                )));
            }
            if a.values().is_empty() {
                return Err(GenerateError::Settings(format!(
                    "agent[{i}]: sets no value (x, y, vx, vy, heading)"
                )));
            }
            if !a.values().iter().all(|(_, v)| v.is_finite()) {
                return Err(GenerateError::Settings(format!(
                    "agent[{i}]: values must be finite"
                )));
            }
            if let Some(c) = &a.category
                && umgen_scene::AgentCategory::from_name(c).is_none()
            {
                return Err(GenerateError::Settings(format!(
                    "agent[{i}].category = {c:?}: expected vehicle, pedestrian or cyclist"
                )));
            }
        }
        Ok(())
    }

    /// The entries that can apply to a rollout of `horizon` generated frames of a model that predicts an
    /// ego action (`ego_action`) and has `agent_slots` agent slots (`None`: no agent modality), and a
    /// description of each entry that cannot, in whole or in part (naming it as `ego[i]` or `agent[i]`, by
    /// its place in the file). Entries that run past the horizon keep their frames within it.
    pub fn applicable(
        &self,
        horizon: usize,
        ego_action: bool,
        agent_slots: Option<usize>,
    ) -> (Control, Vec<String>) {
        let mut problems = Vec::new();
        let mut past = |what: String, from: usize, to: usize| {
            if from >= horizon {
                problems.push(format!(
                    "{what} (frames {from} to {to}) starts after the last generated frame, {}",
                    horizon.saturating_sub(1)
                ));
                false
            } else {
                if to > horizon {
                    problems.push(format!(
                        "{what} (frames {from} to {to}) runs past the last generated frame, {}: frames {horizon} to {to} do not apply",
                        horizon - 1
                    ));
                }
                true
            }
        };
        let mut ego = Vec::new();
        for (i, e) in self.ego.iter().enumerate() {
            if past(format!("ego[{i}]"), e.from, e.to) {
                ego.push(e.clone());
            }
        }
        let mut agent = Vec::new();
        for (i, a) in self.agent.iter().enumerate() {
            if past(format!("agent[{i}]"), a.from, a.to) {
                agent.push((i, a.clone()));
            }
        }
        if !ego_action && !ego.is_empty() {
            problems.push(format!(
                "{} ego entr(ies): this model predicts no ego action",
                ego.len()
            ));
            ego.clear();
        }
        agent.retain(|(i, a)| match agent_slots {
            None => {
                problems.push(format!("agent[{i}]: this model has no agent modality"));
                false
            }
            Some(n) if a.slot >= n => {
                problems.push(format!(
                    "agent[{i}].slot = {}: this model has slots 0 to {}",
                    a.slot,
                    n.saturating_sub(1)
                ));
                false
            }
            Some(_) => true,
        });
        let agent = agent.into_iter().map(|(_, a)| a).collect();
        (Control { ego, agent }, problems)
    }

    /// The agent controls active at generated frame `k`.
    pub fn agents_at(&self, k: usize) -> impl Iterator<Item = &AgentControl> {
        self.agent.iter().filter(move |a| a.from <= k && k < a.to)
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
    fn entries_that_cannot_apply_are_named() {
        let text = "[[ego]]\nfrom = 50\nto = 60\ndx = 2.0\n[[ego]]\nfrom = 0\nto = 4\ndx = 1.0\n\
                    [[agent]]\nslot = 99\nfrom = 0\nto = 1\nx = 3.0\n[[agent]]\nslot = 2\nfrom = 1\nto = 2\nx = 3.0\n";
        let c: Control = toml::from_str(text).unwrap();
        c.validate().unwrap();
        let (kept, problems) = c.applicable(2, true, Some(10));
        assert_eq!(
            problems,
            [
                "ego[0] (frames 50 to 60) starts after the last generated frame, 1",
                "ego[1] (frames 0 to 4) runs past the last generated frame, 1: frames 2 to 4 do not apply",
                "agent[0].slot = 99: this model has slots 0 to 9",
            ]
        );
        assert_eq!(kept.ego, [c.ego[1].clone()]);
        assert_eq!(kept.agent, [c.agent[1].clone()]);
        // Everything applies to a long enough rollout of a model with the slots and the ego action.
        let (all, none) = Control {
            agent: vec![c.agent[1].clone()],
            ..c.clone()
        }
        .applicable(60, true, Some(10));
        assert!(none.is_empty() && all.ego.len() == 2, "{none:?}");
        let (kept, problems) = c.applicable(60, false, None);
        assert!(kept.ego.is_empty() && kept.agent.is_empty());
        assert_eq!(problems.len(), 3, "{problems:?}");
        assert!(problems[0].contains("2 ego entr(ies)") && problems[1].contains("no agent modality"));
    }

    #[test]
    fn ranges_bins_and_errors() {
        let c = Control {
            agent: Vec::new(),
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
            agent: Vec::new(),
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("ego[1] overlaps ego[0]")
        );
    }

    #[test]
    fn agent_entries_are_checked() {
        let text = "[[agent]]\nslot = 2\nfrom = 1\nto = 3\nvx = 6.0\n[[agent]]\nslot = 4\nfrom = 0\nto = 1\ncategory = \"cyclist\"\ny = 2.0\n";
        let c: Control = toml::from_str(text).unwrap();
        c.validate().unwrap();
        assert_eq!(c.agents_at(0).map(|a| a.slot).collect::<Vec<_>>(), [4]);
        assert_eq!(c.agents_at(2).map(|a| a.slot).collect::<Vec<_>>(), [2]);
        assert_eq!(c.agent[0].values(), [("vx", 6.0)]);
        let empty: Control = toml::from_str("[[agent]]\nslot = 0\nfrom = 0\nto = 2\n").unwrap();
        assert!(
            empty
                .validate()
                .unwrap_err()
                .to_string()
                .contains("agent[0]: sets no value")
        );
        let cat: Control =
            toml::from_str("[[agent]]\nslot = 0\nfrom = 0\nto = 2\nx = 1.0\ncategory = \"bus\"\n").unwrap();
        assert!(
            cat.validate()
                .unwrap_err()
                .to_string()
                .contains("agent[0].category = \"bus\"")
        );
        assert!(toml::from_str::<Control>("[[agent]]\nslot = 0\nfrom = 0\nto = 2\nspeed = 1.0\n").is_err());
    }
}
