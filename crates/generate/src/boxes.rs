//! The rule for new agents: when a slot that was empty in the previous frame is filled, its BEV box is
//! decoded and tested against the boxes decoded before it in the frame (the ego's first); a new agent that
//! overlaps one, or that would exceed the frame's box budget, is dropped (its slot becomes pad). That is
//! the official code's rule, which leaves a new agent on an old one whose slot comes later in the frame;
//! [`GroupBoxes::whole_frame`] closes that gap: an old agent's box, once decoded, also drops every new
//! agent before it that it overlaps. Agents that existed before, and agents placed by a control file, are
//! never dropped.

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
    /// Whether a new agent must also clear the old agents decoded after it (in later slots), not only
    /// the boxes before it.
    pub whole_frame: bool,
}

/// How one value of a group is read: its index in the group, its bins' range and their count.
pub(crate) type Field = (usize, f64, f64, u32);

/// The value `field` holds in the group `tokens`: the centre of its bin; `None` where the token is not
/// a value (pad, a category) or the group is too short.
pub(crate) fn field_value(tokens: &[u32], (i, lo, hi, bins): Field) -> Option<f64> {
    tokens
        .get(i)
        .filter(|id| **id < bins)
        .map(|&id| lo + (f64::from(id) + 0.5) * (hi - lo) / f64::from(bins))
}

impl GroupBoxes {
    fn decode(&self, tokens: &[u32]) -> Option<Agent> {
        let v = self.fields.map(|f| field_value(tokens, f));
        Some(bev_box(v[0]?, v[1]?, v[2]?, v[3]?, v[4]?))
    }
}

/// A box held in a frame: the agent's, and the first position of its group if it is a new agent (which
/// an old agent decoded later may still drop).
#[derive(Debug)]
struct Held {
    agent: Agent,
    new_at: Option<usize>,
}

/// What the rule makes of a finished group.
#[derive(Debug, Default, PartialEq, Eq)]
pub(crate) struct Verdict {
    /// The group itself becomes pad.
    pub(crate) drop: bool,
    /// The first positions of new agents decoded before it that become pad.
    pub(crate) emptied: Vec<usize>,
}

/// The boxes decoded so far in the new frame of each scene.
#[derive(Debug)]
pub(crate) struct FrameBoxes {
    boxes: Vec<Vec<Held>>,
}

impl FrameBoxes {
    /// `m` scenes, each starting with the ego box.
    pub(crate) fn new(m: usize, ego: [f64; 2]) -> Self {
        Self {
            boxes: (0..m)
                .map(|_| {
                    vec![Held {
                        agent: bev_box(0.0, 0.0, 0.0, ego[0], ego[1]),
                        new_at: None,
                    }]
                })
                .collect(),
        }
    }

    /// Takes in the finished group `tokens` of scene `b`, which starts at position `start`: whether it
    /// must be emptied (a `newborn` agent that collides or exceeds the budget) and which new agents
    /// before it must be (with [`GroupBoxes::whole_frame`], those an old agent overlaps). Kept groups add
    /// their box.
    pub(crate) fn admit(
        &mut self,
        b: usize,
        start: usize,
        tokens: &[u32],
        spec: &GroupBoxes,
        newborn: bool,
    ) -> Verdict {
        let mut verdict = Verdict::default();
        let Some(a) = spec.decode(tokens) else {
            return verdict;
        };
        let boxes = &mut self.boxes[b];
        if newborn {
            if boxes.len() >= spec.max_boxes || boxes.iter().any(|o| overlap(&o.agent, &a)) {
                verdict.drop = true;
                return verdict;
            }
        } else if spec.whole_frame {
            boxes.retain(|o| match o.new_at {
                Some(at) if overlap(&o.agent, &a) => {
                    verdict.emptied.push(at);
                    false
                }
                _ => true,
            });
        }
        boxes.push(Held {
            agent: a,
            new_at: newborn.then_some(start),
        });
        verdict
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// x, y, heading, length, width at 0..5; x and y in 11 bins of 10 m centred on 0 (bin 5 → 0 m).
    fn spec(whole_frame: bool) -> GroupBoxes {
        GroupBoxes {
            fields: [
                (0, -55.0, 55.0, 11),
                (1, -55.0, 55.0, 11),
                (2, -3.2, 3.2, 10),
                (3, 0.0, 10.0, 10),
                (4, 0.0, 5.0, 10),
            ],
            ego: [4.6, 1.9],
            max_boxes: 4,
            whole_frame,
        }
    }

    fn dropped(v: Verdict) -> bool {
        assert!(v.emptied.is_empty(), "{v:?}");
        v.drop
    }

    #[test]
    fn new_agents_on_others_or_over_budget_are_dropped_old_ones_kept() {
        let spec = spec(false);
        let mut f = FrameBoxes::new(1, spec.ego);
        assert!(
            dropped(f.admit(0, 0, &[5, 5, 5, 4, 3], &spec, true)),
            "a new agent on the ego goes"
        );
        let clear = [6, 6, 5, 4, 3]; // at (10, 10) m
        assert!(
            !dropped(f.admit(0, 5, &clear, &spec, true)),
            "a free new agent stays"
        );
        assert!(
            dropped(f.admit(0, 10, &clear, &spec, true)),
            "a new agent on top of it goes"
        );
        assert!(
            !dropped(f.admit(0, 15, &clear, &spec, false)),
            "an old agent stays even when it overlaps, and without the whole frame empties nothing"
        );
        assert!(
            !dropped(f.admit(0, 20, &[0, 0, 5, 4, 3], &spec, true)),
            "the fourth box fits the budget"
        );
        assert!(
            dropped(f.admit(0, 25, &[10, 10, 5, 4, 3], &spec, true)),
            "a fifth new one does not"
        );
        assert!(
            !dropped(f.admit(0, 30, &[11, 5, 5, 4, 3], &spec, true)),
            "undecodable groups are left alone"
        );
    }

    #[test]
    fn with_the_whole_frame_an_old_agent_empties_the_new_ones_before_it_that_it_overlaps() {
        let spec = spec(true);
        let mut f = FrameBoxes::new(1, spec.ego);
        let (here, there) = ([6, 6, 5, 4, 3], [4, 4, 5, 4, 3]); // (10, 10) and (-10, -10) m
        assert_eq!(f.admit(0, 5, &here, &spec, true), Verdict::default());
        assert_eq!(f.admit(0, 10, &there, &spec, true), Verdict::default());
        // An old agent on the first new one: that one goes, the old one stays.
        let v = f.admit(0, 15, &here, &spec, false);
        assert_eq!(
            v,
            Verdict {
                drop: false,
                emptied: vec![5]
            }
        );
        // A new agent on the old one goes, as before.
        assert!(f.admit(0, 20, &here, &spec, true).drop);
        // The budget counts the boxes left (the ego, the second new agent, the old one): a fourth fits.
        assert_eq!(f.admit(0, 25, &[0, 0, 5, 4, 3], &spec, true), Verdict::default());
        // Another old agent on the same spot empties nothing (old agents are never emptied).
        assert_eq!(f.admit(0, 30, &here, &spec, false), Verdict::default());
    }
}
