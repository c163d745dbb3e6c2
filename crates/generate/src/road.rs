//! The road rule for entering vehicles (`umgen generate --entering-on-road`): once a frame is decoded, a
//! vehicle in a slot that was empty in the scene's frame before is emptied (its group becomes pad) when
//! its centre lies off the drivable area that the frame's own map draws.
//!
//! The model places entering vehicles where vehicles usually enter, at the edge of the agents' range,
//! and on road networks it has not seen most of them land beside the road (docs/results.md); agents that
//! were in the frame before, pedestrians and cyclists, and agents placed by the caller are never tested.
//! The rule runs on the decoded frame, outside the decoders, so the burn decoder and the engine apply it
//! alike. The frame's later tokens (later slots, the camera) were drawn with the vehicle present; the
//! next frame's history no longer holds it, and the slot is free to be filled again.

use crate::boxes::{Field, field_value};
use crate::error::{GenerateError, Result};
use crate::rules::TokenGroups;

/// Where entering vehicles may stand in one frame, in its ego coordinates.
pub trait Area {
    /// Whether the point `p` (m, ego frame) lies on the area; `None` where the area does not say (beyond
    /// the raster it was read from).
    fn covers(&self, p: [f64; 2]) -> Option<bool>;
}

/// What the rule did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct RoadCount {
    /// Entering vehicles tested.
    pub tested: u64,
    /// Of them, emptied: off the area.
    pub dropped: u64,
    /// Of them, kept because the area does not reach their centre.
    pub beyond: u64,
}

impl std::ops::AddAssign for RoadCount {
    fn add_assign(&mut self, o: Self) {
        self.tested += o.tested;
        self.dropped += o.dropped;
        self.beyond += o.beyond;
    }
}

/// The rule over one run of agent groups.
#[derive(Debug, Clone, PartialEq)]
pub struct RoadRule {
    groups: TokenGroups,
    x: Field,
    y: Field,
    vehicle: u32,
}

/// An entering vehicle: its group's first position and its centre (m, ego frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Entering {
    /// The group's first position in the frame.
    pub first: usize,
    /// The centre its x and y tokens decode to (bin centres).
    pub centre: [f64; 2],
}

impl RoadRule {
    /// The rule over `groups`, whose box fields say where x and y are (`TokenGroups::boxes`), for the
    /// category id `vehicle` (one of `groups.last`).
    pub fn new(groups: TokenGroups, vehicle: u32) -> Result<Self> {
        let Some(boxes) = groups.boxes.as_ref() else {
            return Err(GenerateError::Settings(
                "the road rule needs the agent groups' box fields (x and y)".into(),
            ));
        };
        if !groups.last.contains(&vehicle) {
            return Err(GenerateError::Settings(format!(
                "the road rule's vehicle id {vehicle} is not a category id of the agent groups ({:?})",
                groups.last
            )));
        }
        let (x, y) = (boxes.fields[0], boxes.fields[1]);
        if [x.0, y.0].iter().any(|&i| i + 1 >= groups.size) || x.3 == 0 || y.3 == 0 {
            return Err(GenerateError::Settings(format!(
                "the road rule's x and y fields ({}, {}) must be values of groups of {} tokens",
                x.0, y.0, groups.size
            )));
        }
        Ok(Self {
            groups,
            x,
            y,
            vehicle,
        })
    }

    /// The vehicles of `frame` whose group held no agent in `before` (the scene's frame before it), in
    /// slot order; groups holding a position of `placed` (set by the caller) are left out.
    pub fn entering(&self, frame: &[u32], before: &[u32], placed: &[usize]) -> Vec<Entering> {
        let g = &self.groups;
        (0..g.count)
            .filter_map(|k| {
                let first = g.first + k * g.size;
                let now = frame.get(first..first + g.size)?;
                let was = before.get(first..first + g.size)?;
                let entered = was[0] == g.pad && now[g.size - 1] == self.vehicle;
                let free = !placed.iter().any(|p| (first..first + g.size).contains(p));
                let centre = [field_value(now, self.x)?, field_value(now, self.y)?];
                (entered && free).then_some(Entering { first, centre })
            })
            .collect()
    }

    /// Empties each of `entering` (from [`RoadRule::entering`] on `frame`) whose centre `area` puts off it.
    pub fn apply(&self, frame: &mut [u32], entering: &[Entering], area: &dyn Area) -> RoadCount {
        let mut count = RoadCount::default();
        for e in entering {
            count.tested += 1;
            match area.covers(e.centre) {
                Some(true) => {}
                None => count.beyond += 1,
                Some(false) => {
                    if let Some(group) = frame.get_mut(e.first..e.first + self.groups.size) {
                        group.fill(self.groups.pad);
                        count.dropped += 1;
                    }
                }
            }
        }
        count
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::boxes::GroupBoxes;

    /// Two groups of four tokens (x, y, heading, category) from position 1; values 0..8 over [−8, 8) m
    /// (2 m bins), pad 12, categories 8 (vehicle), 9, 10.
    fn rule() -> RoadRule {
        let f = |i| (i, -8.0, 8.0, 8);
        let groups = TokenGroups {
            first: 1,
            size: 4,
            count: 2,
            pad: 12,
            values: 8,
            last: 8..11,
            boxes: Some(GroupBoxes {
                fields: [f(0), f(1), f(2), f(2), f(2)],
                ego: [4.0, 2.0],
                max_boxes: 8,
                whole_frame: true,
            }),
        };
        RoadRule::new(groups, 8).unwrap()
    }

    /// The half-plane y ≥ 0 within 6 m of the ego along x.
    struct LeftHalf;
    impl Area for LeftHalf {
        fn covers(&self, p: [f64; 2]) -> Option<bool> {
            (p[0].abs() <= 6.0).then_some(p[1] >= 0.0)
        }
    }

    #[test]
    fn entering_vehicles_off_the_area_are_emptied() {
        let r = rule();
        // Slot 0 enters at x bin 4 (1 m), y bin 1 (−5 m): off. Slot 1 was there before: never tested.
        let before = [0, 12, 12, 12, 12, 3, 3, 0, 8];
        let mut frame = vec![7, 4, 1, 0, 8, 3, 0, 0, 8];
        let entering = r.entering(&frame, &before, &[]);
        assert_eq!(
            entering,
            vec![Entering {
                first: 1,
                centre: [1.0, -5.0]
            }]
        );
        let count = r.apply(&mut frame, &entering, &LeftHalf);
        assert_eq!(
            count,
            RoadCount {
                tested: 1,
                dropped: 1,
                beyond: 0
            }
        );
        assert_eq!(
            frame,
            [7, 12, 12, 12, 12, 3, 0, 0, 8],
            "slot 0 emptied, the rest as drawn"
        );
        // On the area (y bin 5: 3 m) it stays; beyond the area's reach (x bin 7: 7 m) it stays, counted.
        for (x, y, beyond) in [(4, 5, 0), (7, 1, 1)] {
            let mut frame = vec![7, x, y, 0, 8, 12, 12, 12, 12];
            let e = r.entering(&frame, &before, &[]);
            let count = r.apply(&mut frame, &e, &LeftHalf);
            assert_eq!((count.tested, count.dropped, count.beyond), (1, 0, beyond));
            assert_eq!(frame[1..5], [x, y, 0, 8]);
        }
        // Not tested: a pedestrian entering, a vehicle the caller placed, an empty slot, a malformed group.
        let walker = [7, 4, 1, 0, 9, 12, 12, 12, 12];
        assert!(r.entering(&walker, &before, &[]).is_empty());
        let placed = [7, 4, 1, 0, 8, 12, 12, 12, 12];
        assert!(r.entering(&placed, &before, &[4]).is_empty());
        assert_eq!(
            r.entering(&placed, &before, &[5]).len(),
            1,
            "position 5 is slot 1's"
        );
        assert!(r.entering(&[12; 9], &before, &[]).is_empty());
        let malformed = [7, 12, 1, 0, 8, 12, 12, 12, 12];
        assert!(r.entering(&malformed, &before, &[]).is_empty());
        // A frame shorter than the groups tests nothing rather than failing.
        assert!(r.entering(&[7, 4], &before, &[]).is_empty());
    }

    #[test]
    fn the_rule_needs_box_fields_and_a_vehicle_category() {
        let mut groups = rule().groups;
        assert!(
            RoadRule::new(groups.clone(), 11).is_err(),
            "11 is not a category id"
        );
        groups.boxes = None;
        let err = RoadRule::new(groups, 8).unwrap_err().to_string();
        assert!(err.contains("box fields"), "{err}");
    }
}
