//! The official code's rule for new agents: when a slot that was empty in the previous frame is filled,
//! its BEV box is decoded and tested against the boxes decoded before it in the frame (the ego's first);
//! a new agent that overlaps one, or that would exceed the frame's box budget, is dropped (its slot becomes
//! pad). Agents that existed before, and agents placed by a control file, are never dropped.

use umgen_eval::collision::{bev_box, overlap};
use umgen_scene::Agent;

/// How to read a box from a token group.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupBoxes {
    /// `(index in the group, lo, hi, bins)` of x, y, heading, length and width.
    pub fields: [(usize, f64, f64, u32); 5],
    /// The ego box (length, width) at the origin.
    pub ego: [f64; 2],
    /// Boxes a frame may hold (ego included); new agents beyond it are dropped.
    pub max_boxes: usize,
}

impl GroupBoxes {
    fn decode(&self, tokens: &[u32]) -> Option<Agent> {
        let v = self.fields.map(|(i, lo, hi, bins)| {
            tokens
                .get(i)
                .filter(|id| **id < bins)
                .map(|&id| lo + (f64::from(id) + 0.5) * (hi - lo) / f64::from(bins))
        });
        Some(bev_box(v[0]?, v[1]?, v[2]?, v[3]?, v[4]?))
    }
}

/// The boxes decoded so far in the new frame of each scene.
#[derive(Debug)]
pub(crate) struct FrameBoxes {
    boxes: Vec<Vec<Agent>>,
}

impl FrameBoxes {
    /// `m` scenes, each starting with the ego box.
    pub(crate) fn new(m: usize, ego: [f64; 2]) -> Self {
        Self {
            boxes: vec![vec![bev_box(0.0, 0.0, 0.0, ego[0], ego[1])]; m],
        }
    }

    /// Takes in the finished group `tokens` of scene `b`; returns whether it must be emptied (a `newborn`
    /// agent that collides or exceeds the budget). Kept groups add their box.
    pub(crate) fn admit(&mut self, b: usize, tokens: &[u32], spec: &GroupBoxes, newborn: bool) -> bool {
        let Some(a) = spec.decode(tokens) else {
            return false;
        };
        let boxes = &mut self.boxes[b];
        if newborn && (boxes.len() >= spec.max_boxes || boxes.iter().any(|o| overlap(o, &a))) {
            return true;
        }
        boxes.push(a);
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_agents_on_others_or_over_budget_are_dropped_old_ones_kept() {
        // x, y, heading, length, width at 0..5; x and y in 11 bins of 10 m centred on 0 (bin 5 → 0 m).
        let spec = GroupBoxes {
            fields: [
                (0, -55.0, 55.0, 11),
                (1, -55.0, 55.0, 11),
                (2, -3.2, 3.2, 10),
                (3, 0.0, 10.0, 10),
                (4, 0.0, 5.0, 10),
            ],
            ego: [4.6, 1.9],
            max_boxes: 4,
        };
        let mut f = FrameBoxes::new(1, spec.ego);
        assert!(
            f.admit(0, &[5, 5, 5, 4, 3], &spec, true),
            "a new agent on the ego goes"
        );
        let clear = [6, 6, 5, 4, 3]; // at (10, 10) m
        assert!(!f.admit(0, &clear, &spec, true), "a free new agent stays");
        assert!(f.admit(0, &clear, &spec, true), "a new agent on top of it goes");
        assert!(
            !f.admit(0, &clear, &spec, false),
            "an old agent stays even when it overlaps"
        );
        assert!(
            !f.admit(0, &[0, 0, 5, 4, 3], &spec, true),
            "the fourth box fits the budget"
        );
        assert!(
            f.admit(0, &[10, 10, 5, 4, 3], &spec, true),
            "a fifth new one does not"
        );
        assert!(
            !f.admit(0, &[11, 5, 5, 4, 3], &spec, true),
            "undecodable groups are left alone"
        );
    }
}
