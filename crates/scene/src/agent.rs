//! Traffic agents around the ego vehicle.

use crate::pose::{Pose2, wrap_angle};
use serde::{Deserialize, Serialize};

/// What kind of road user an agent is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AgentCategory {
    /// Cars, trucks, buses, motorbikes.
    Vehicle,
    /// People on foot.
    Pedestrian,
    /// Bicycles.
    Cyclist,
}

impl AgentCategory {
    /// Every category, in token order (vehicle, pedestrian, cyclist).
    pub const ALL: [AgentCategory; 3] = [
        AgentCategory::Vehicle,
        AgentCategory::Pedestrian,
        AgentCategory::Cyclist,
    ];

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            AgentCategory::Vehicle => "vehicle",
            AgentCategory::Pedestrian => "pedestrian",
            AgentCategory::Cyclist => "cyclist",
        }
    }

    /// The category whose [`AgentCategory::name`] is `name`; `None` for any other string.
    pub fn from_name(name: &str) -> Option<AgentCategory> {
        AgentCategory::ALL.into_iter().find(|c| c.name() == name)
    }

    /// Position in [`AgentCategory::ALL`].
    pub fn index(self) -> usize {
        match self {
            AgentCategory::Vehicle => 0,
            AgentCategory::Pedestrian => 1,
            AgentCategory::Cyclist => 2,
        }
    }
}

/// One agent's state at one frame, in that frame's ego coordinates (x forward, y left, z up).
///
/// Velocities are the agent's own (ground) velocity rotated into the ego frame, not its velocity
/// relative to the moving ego.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Agent {
    /// Track id, stable across the frames of a clip.
    pub track_id: u64,
    /// Category.
    pub category: AgentCategory,
    /// Box centre x (m).
    pub x: f64,
    /// Box centre y (m).
    pub y: f64,
    /// Box centre z (m).
    pub z: f64,
    /// Velocity x (m/s).
    pub vx: f64,
    /// Velocity y (m/s).
    pub vy: f64,
    /// Velocity z (m/s).
    pub vz: f64,
    /// Heading in the ego frame (radians, [-π, π)).
    pub heading: f64,
    /// Box length along the heading (m).
    pub length: f64,
    /// Box width (m).
    pub width: f64,
    /// Box height (m).
    pub height: f64,
}

impl Agent {
    /// Planar distance from the ego origin.
    pub fn distance(&self) -> f64 {
        self.x.hypot(self.y)
    }

    /// The same agent expressed in another ego frame. `from` is the pose of the frame the agent is
    /// currently expressed in and `to` the pose of the target frame, both in one common (global) frame.
    pub fn reframe(&self, from: &Pose2, to: &Pose2) -> Agent {
        let [gx, gy] = from.to_parent([self.x, self.y]);
        let [x, y] = to.to_local([gx, gy]);
        let gv = from.rotate_to_parent([self.vx, self.vy]);
        let [vx, vy] = to.rotate_to_local(gv);
        Agent {
            x,
            y,
            vx,
            vy,
            heading: wrap_angle(self.heading + from.heading - to.heading),
            ..*self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn reframe_moves_an_agent_between_ego_frames() {
        // In ego frame A (global origin facing +x) an agent is 10 m ahead, driving forward at 5 m/s.
        let a = Pose2::new(0.0, 0.0, 0.0);
        let agent = Agent {
            track_id: 3,
            category: AgentCategory::Vehicle,
            x: 10.0,
            y: 0.0,
            z: 0.0,
            vx: 5.0,
            vy: 0.0,
            vz: 0.0,
            heading: 0.0,
            length: 4.5,
            width: 1.9,
            height: 1.6,
        };
        // Ego frame B: 4 m further, turned left by 90°: the agent is 6 m to B's right, moving rightwards.
        let b = Pose2::new(4.0, 0.0, PI / 2.0);
        let r = agent.reframe(&a, &b);
        assert!((r.x - 0.0).abs() < 1e-9 && (r.y + 6.0).abs() < 1e-9, "{r:?}");
        assert!((r.vx - 0.0).abs() < 1e-9 && (r.vy + 5.0).abs() < 1e-9);
        assert!((r.heading + PI / 2.0).abs() < 1e-9);
        assert_eq!((r.track_id, r.length), (3, 4.5));
        let back = r.reframe(&b, &a);
        assert!((back.x - 10.0).abs() < 1e-9 && back.y.abs() < 1e-9);
    }

    #[test]
    fn category_names_round_trip_through_serde() {
        for c in AgentCategory::ALL {
            let s = serde_json::to_string(&c).unwrap();
            assert_eq!(s, format!("\"{}\"", c.name()));
            assert_eq!(serde_json::from_str::<AgentCategory>(&s).unwrap(), c);
            assert_eq!(AgentCategory::ALL[c.index()], c);
            assert_eq!(AgentCategory::from_name(c.name()), Some(c));
        }
        assert_eq!(AgentCategory::from_name("Vehicle"), None);
        assert_eq!(AgentCategory::from_name("bus"), None);
    }
}
