//! Vehicles leaving the road: on the drivable area in one frame and off it in the next. How fast they go
//! and how far their heading turned over the frames before tells a vehicle driven straight on where the
//! road bends (its heading kept) from one turned off the road, or one standing while the road under it
//! moved.

use crate::counts::rate_95;
use crate::horizon::MOVING_M_S;
use crate::l2::{global_position, median};
use crate::offroad::Drivable;
use serde::Serialize;
use umgen_scene::{Agent, AgentCategory, Frame, wrap_angle};

/// Frames before the one off the road over which a vehicle's turn is measured.
pub const TURN_FRAMES: usize = 4;

/// Vehicles leaving the road, gathered frame by frame.
#[derive(Debug, Clone, Default)]
pub struct Leaving {
    count: usize,
    moving: usize,
    /// Per moving vehicle that left, the largest change of its global heading (degrees) between the frame
    /// off the road and each of the [`TURN_FRAMES`] frames before it that hold it.
    turns: Vec<f64>,
}

/// What [`Leaving`] gathered, as reported.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LeavingCounts {
    /// Vehicles on the drivable area in a frame and off it in the next.
    pub vehicles: usize,
    /// Of them, those moving (above [`MOVING_M_S`]) in the frame off the road.
    pub moving: usize,
    /// 95 % interval of `vehicles` per second ([`rate_95`]); `None` without time.
    pub per_s_95: Option<[f64; 2]>,
    /// Median over the moving ones of the largest turn of the heading (degrees) over the
    /// [`TURN_FRAMES`] frames before: near 0 for vehicles driven straight off the road.
    pub turn_median_deg: Option<f64>,
}

/// The global heading of `a` in a frame whose ego is `f`'s.
fn heading(f: &Frame, a: &Agent) -> f64 {
    f.ego.heading + a.heading
}

impl Leaving {
    /// Adds `frame`, with the frames before it in its sequence (the last one just before it), against
    /// the drivable area of their map.
    pub fn add(&mut self, frame: &Frame, before: &[Frame], drivable: &Drivable) {
        let Some(prev) = before.last() else {
            return;
        };
        let on = |f: &Frame, a: &Agent| drivable.contains(global_position(&f.ego, a));
        for a in frame
            .agents
            .iter()
            .filter(|a| a.category == AgentCategory::Vehicle)
        {
            let was_on = prev
                .agents
                .iter()
                .find(|b| b.track_id == a.track_id)
                .is_some_and(|b| b.category == AgentCategory::Vehicle && on(prev, b));
            if !was_on || on(frame, a) {
                continue;
            }
            self.count += 1;
            if a.vx.hypot(a.vy) <= MOVING_M_S {
                continue;
            }
            self.moving += 1;
            let now = heading(frame, a);
            let turn = before
                .iter()
                .rev()
                .take(TURN_FRAMES)
                .filter_map(|f| f.agents.iter().find(|b| b.track_id == a.track_id).map(|b| (f, b)))
                .map(|(f, b)| wrap_angle(now - heading(f, b)).abs())
                .fold(0.0, f64::max);
            self.turns.push(turn.to_degrees());
        }
    }

    /// The counts over `seconds` of transitions.
    pub fn counts(&self, seconds: f64) -> LeavingCounts {
        LeavingCounts {
            vehicles: self.count,
            moving: self.moving,
            per_s_95: rate_95(self.count, seconds),
            turn_median_deg: median(&self.turns),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::collision::bev_box;
    use umgen_scene::{EgoPose, RoadNetwork};

    fn car(id: u64, x: f64, y: f64, speed: f64, heading: f64) -> Agent {
        Agent {
            track_id: id,
            category: AgentCategory::Vehicle,
            vx: speed * heading.cos(),
            vy: speed * heading.sin(),
            ..bev_box(x, y, heading, 4.0, 2.0)
        }
    }

    fn frame(ego_heading: f64, agents: Vec<Agent>) -> Frame {
        Frame {
            ego: EgoPose {
                heading: ego_heading,
                ..EgoPose::default()
            },
            agents,
            ..Frame::default()
        }
    }

    #[test]
    fn vehicles_that_leave_the_road_and_how_they_turned() {
        // A road 10 m wide along global x; the ego turns by 0.1 rad a frame, which the agents' own
        // headings (ego frame) undo for those that keep their global heading.
        let road = Drivable::new(&RoadNetwork {
            lanes: vec![vec![[-100.0, -5.0], [100.0, -5.0], [100.0, 5.0], [-100.0, 5.0]]],
            ..RoadNetwork::default()
        });
        // Global positions put in the ego frame of a frame whose ego (at the origin) has heading `e`.
        let at = |e: f64, id: u64, x: f64, y: f64, speed: f64, h: f64| {
            let (c, s) = (e.cos(), e.sin());
            car(id, c * x + s * y, -s * x + c * y, speed, h - e)
        };
        let walker = |e: f64, x: f64, y: f64| Agent {
            category: AgentCategory::Pedestrian,
            ..at(e, 9, x, y, 1.5, 0.0)
        };
        let frames: Vec<Frame> = (0..3)
            .map(|k| {
                let e = 0.1 * k as f64;
                let t = k as f64;
                let mut agents = vec![
                    // 1 drifts across the edge keeping its heading (0.05 rad off the road's axis).
                    at(e, 1, 10.0 * t, 2.0 + 2.0 * t, 10.0, 0.05),
                    // 2 turns off: its heading goes 0, 0.2, 0.5.
                    at(e, 2, 20.0, 0.0 + 3.0 * t, 8.0, [0.0, 0.2, 0.5][k]),
                    // 3 stands; the last frame puts it just off the road.
                    at(e, 3, -30.0, if k < 2 { 4.0 } else { 5.5 }, 0.0, 0.0),
                    // 4 is off the road throughout.
                    at(e, 4, 0.0, 30.0, 10.0, 0.0),
                    walker(e, -10.0, 4.0 + 1.0 * t),
                ];
                // 5 enters off the road in the last frame.
                if k == 2 {
                    agents.push(at(e, 5, 40.0, 20.0, 10.0, 0.0));
                }
                frame(e, agents)
            })
            .collect();
        let mut l = Leaving::default();
        for k in 0..3 {
            l.add(&frames[k], &frames[..k], &road);
        }
        // Frame 1: 1 at y 4 on, 2 at y 3 on. Frame 2: 1 at y 6 off (straight), 2 at y 6 off (turned
        // 0.5 rad since frame 0), 3 at y 5.5 off (standing).
        let c = l.counts(1.0);
        assert_eq!((c.vehicles, c.moving), (3, 2), "{c:?}");
        assert_eq!(l.turns.len(), 2);
        assert!(l.turns[0].abs() < 1e-9, "{:?}", l.turns);
        assert!((l.turns[1] - 0.5f64.to_degrees()).abs() < 1e-9, "{:?}", l.turns);
        assert!(
            (c.turn_median_deg.unwrap() - 0.25f64.to_degrees()).abs() < 1e-9,
            "{c:?}"
        );
        let [lo, hi] = c.per_s_95.unwrap();
        assert!(lo < 3.0 && 3.0 < hi, "{c:?}");
        assert_eq!(Leaving::default().counts(0.0).per_s_95, None);
    }
}
