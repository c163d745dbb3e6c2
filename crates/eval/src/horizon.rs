//! Scene statistics over a rollout's horizon, in the same terms for generated rollouts and real clips:
//! agents per frame (mean and distribution), agents entering and leaving per second, the collision and
//! off-road rates, the collisions that begin (and how many of them at speed into a standing agent), how
//! far moving agents' headings are from their direction of motion, the speed and acceleration
//! distributions, and how fast agents are when they enter. [`SceneStats`] gathers them frame
//! by frame, each frame with the one before it in its sequence (entries, exits and accelerations need
//! both); [`SceneStats::summary`] reports them.

use crate::collision::{colliding, collision_onsets};
use crate::l2::{global_position, global_velocity, median, quantile};
use crate::offroad::Drivable;
use serde::Serialize;
use std::collections::HashMap;
use umgen_scene::{AgentCategory, Frame, wrap_angle};

/// Speed (m/s) above which an agent counts as moving, for the heading–motion angle: below it a velocity's
/// direction is mostly noise of the data (or of the velocity bins).
pub const MOVING_M_S: f64 = 1.0;

/// Statistics gathered over frames.
#[derive(Debug, Clone, Default)]
pub struct SceneStats {
    /// Agents in each frame.
    counts: Vec<usize>,
    /// Frames that had a previous frame, and the agents entering and leaving between the two.
    transitions: usize,
    entries: usize,
    exits: usize,
    /// Seconds between the frames of the transitions.
    seconds: f64,
    /// Per frame with agents, the fraction that overlaps another.
    collision_rates: Vec<f64>,
    /// Collisions begun between consecutive frames, and those driven at speed into a standing agent.
    onsets: usize,
    onsets_standing: usize,
    /// Agents tested against a map, and those off its drivable area.
    on_map: usize,
    off_road: usize,
    /// The same for vehicles alone: pedestrians walk off the drivable area, vehicles do not.
    vehicles_on_map: usize,
    vehicles_off_road: usize,
    /// Vehicles tested against a map in the frame they entered, and those off its drivable area.
    entering_on_map: usize,
    entering_off_road: usize,
    /// Frames tested against a map, and those whose ego is off its drivable area.
    ego_on_map: usize,
    ego_off_road: usize,
    /// Degrees between heading and direction of motion of moving agents.
    heading_motion: Vec<f64>,
    speeds: Vec<f64>,
    /// Magnitude of the change of global velocity (m/s²) of agents in consecutive frames.
    accelerations: Vec<f64>,
    /// Speeds (m/s) of agents in the frame they entered.
    entry_speeds: Vec<f64>,
}

/// Mean, 10th, 50th and 90th percentile of a distribution.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Spread {
    /// Mean.
    pub mean: f64,
    /// 10th percentile.
    pub p10: f64,
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
}

impl Spread {
    fn of(v: &[f64]) -> Option<Self> {
        Some(Self {
            mean: v.iter().sum::<f64>() / v.len().max(1) as f64,
            p10: quantile(v, 0.1)?,
            p50: median(v)?,
            p90: quantile(v, 0.9)?,
        })
    }
}

/// What [`SceneStats`] gathered, as reported.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// Frames.
    pub frames: usize,
    /// Mean agents per frame.
    pub agents_mean: Option<f64>,
    /// Fraction of frames with 0, 1, 2, … agents.
    pub agents_distribution: Vec<f64>,
    /// Agents entering per second (present in a frame, absent from the one before).
    pub entries_per_s: Option<f64>,
    /// Agents leaving per second (present in a frame, absent from the next).
    pub exits_per_s: Option<f64>,
    /// Mean over frames with agents of the fraction that overlaps another (the authors' ratio).
    pub collision_rate: Option<f64>,
    /// Collisions begun per second: pairs of agents whose boxes overlap in a frame and did not in the
    /// one before.
    pub collision_onsets_per_s: Option<f64>,
    /// Of those, the fraction driven at speed into a standing agent
    /// ([`crate::collision::INTO_STANDING_M_S`]: one below [`MOVING_M_S`], the other above 5 m/s before
    /// the step). `None` without onsets.
    pub onsets_into_standing: Option<f64>,
    /// Fraction of agents whose centre is off the drivable area (lanes, connectors, intersections) of
    /// the scene's map; `None` without maps.
    pub off_road_rate: Option<f64>,
    /// The same for vehicles alone (pedestrians walk beside the roads, so a change of the pedestrian
    /// share moves `off_road_rate` without any vehicle leaving the road); `None` without maps.
    pub vehicle_off_road_rate: Option<f64>,
    /// Of the vehicles entering (in the frame they entered), the fraction whose centre is off the
    /// drivable area: where a generated scene places its new vehicles. `None` without maps or entries.
    pub entering_off_road_rate: Option<f64>,
    /// Fraction of frames whose ego is off the drivable area of the scene's map: agents are placed
    /// relative to the ego, so an ego that leaves the road carries them off it too.
    pub ego_off_road_rate: Option<f64>,
    /// Median angle (degrees) between heading and direction of motion of agents faster than
    /// [`MOVING_M_S`].
    pub heading_motion_median_deg: Option<f64>,
    /// Agents' speeds (m/s).
    pub speed: Option<Spread>,
    /// Agents' accelerations (m/s²), from their global velocities in consecutive frames.
    pub acceleration: Option<Spread>,
    /// Speeds (m/s) of entering agents, in the frame they entered.
    pub entry_speed: Option<Spread>,
}

impl SceneStats {
    /// Adds `frame`, with the frame `dt` seconds before it in its sequence (`None` at a sequence's start)
    /// and the drivable area of its map, if known.
    pub fn add(&mut self, frame: &Frame, before: Option<&Frame>, dt: f64, drivable: Option<&Drivable>) {
        let agents = &frame.agents;
        self.counts.push(agents.len());
        if let Some(d) = drivable {
            self.ego_on_map += 1;
            self.ego_off_road += usize::from(!d.contains([frame.ego.x, frame.ego.y]));
        }
        if !agents.is_empty() {
            let (hit, n) = colliding(agents);
            self.collision_rates.push(hit as f64 / n as f64);
        }
        // Per agent, whether it is a vehicle off the road (for the entering ones below).
        let mut vehicle_off = Vec::with_capacity(agents.len());
        for a in agents {
            let speed = a.vx.hypot(a.vy);
            self.speeds.push(speed);
            if speed > MOVING_M_S {
                let angle = wrap_angle(a.heading - a.vy.atan2(a.vx)).abs();
                self.heading_motion.push(angle.to_degrees());
            }
            let vehicle = a.category == AgentCategory::Vehicle;
            let off = drivable.map(|d| !d.contains(global_position(&frame.ego, a)));
            if let Some(off) = off {
                self.on_map += 1;
                self.off_road += usize::from(off);
                if vehicle {
                    self.vehicles_on_map += 1;
                    self.vehicles_off_road += usize::from(off);
                }
            }
            vehicle_off.push(off.filter(|_| vehicle));
        }
        let Some(before) = before else {
            return;
        };
        let earlier: HashMap<u64, [f64; 2]> = before
            .agents
            .iter()
            .map(|a| (a.track_id, global_velocity(&before.ego, a)))
            .collect();
        let mut stayed = 0;
        for (a, off) in agents.iter().zip(vehicle_off) {
            if let Some(v0) = earlier.get(&a.track_id) {
                stayed += 1;
                let v1 = global_velocity(&frame.ego, a);
                self.accelerations.push((v1[0] - v0[0]).hypot(v1[1] - v0[1]) / dt);
            } else {
                self.entry_speeds.push(a.vx.hypot(a.vy));
                if let Some(off) = off {
                    self.entering_on_map += 1;
                    self.entering_off_road += usize::from(off);
                }
            }
        }
        let (onsets, standing) = collision_onsets(&before.agents, agents);
        self.onsets += onsets;
        self.onsets_standing += standing;
        self.transitions += 1;
        self.seconds += dt;
        self.entries += agents.len() - stayed;
        self.exits += before.agents.len() - stayed;
    }

    /// The statistics gathered.
    pub fn summary(&self) -> Summary {
        let frames = self.counts.len();
        let max = self.counts.iter().copied().max().unwrap_or(0);
        let mut distribution = vec![0.0; if frames == 0 { 0 } else { max + 1 }];
        for &c in &self.counts {
            distribution[c] += 1.0 / frames as f64;
        }
        let per_s = |n: usize| (self.seconds > 0.0).then(|| n as f64 / self.seconds);
        let share = |n: usize, of: usize| (of > 0).then(|| n as f64 / of as f64);
        let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
        let counts: Vec<f64> = self.counts.iter().map(|&c| c as f64).collect();
        Summary {
            frames,
            agents_mean: mean(&counts),
            agents_distribution: distribution,
            entries_per_s: per_s(self.entries),
            exits_per_s: per_s(self.exits),
            collision_rate: mean(&self.collision_rates),
            collision_onsets_per_s: per_s(self.onsets),
            onsets_into_standing: share(self.onsets_standing, self.onsets),
            off_road_rate: share(self.off_road, self.on_map),
            vehicle_off_road_rate: share(self.vehicles_off_road, self.vehicles_on_map),
            entering_off_road_rate: share(self.entering_off_road, self.entering_on_map),
            ego_off_road_rate: share(self.ego_off_road, self.ego_on_map),
            heading_motion_median_deg: median(&self.heading_motion),
            speed: Spread::of(&self.speeds),
            acceleration: Spread::of(&self.accelerations),
            entry_speed: Spread::of(&self.entry_speeds),
        }
    }
}

/// The second of the horizon that generated frame `h` (1 = the first generated frame) falls in, for
/// frames `dt` seconds apart: second 1 holds the frames up to 1 s after the context, and so on.
pub fn second_of(h: usize, dt: f64) -> usize {
    // A hair below the frame's time, so that the frame at exactly 1.0 s belongs to second 1.
    ((h as f64 * dt - 1e-9).ceil() as usize).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::collision::bev_box;
    use umgen_scene::{Agent, EgoPose, RoadNetwork};

    fn agent(id: u64, x: f64, y: f64, vx: f64, vy: f64, heading: f64) -> Agent {
        Agent {
            track_id: id,
            vx,
            vy,
            ..bev_box(x, y, heading, 4.0, 2.0)
        }
    }

    fn frame(heading: f64, agents: Vec<Agent>) -> Frame {
        Frame {
            ego: EgoPose {
                x: 0.0,
                y: 0.0,
                heading,
                speed: 0.0,
            },
            agents,
            ..Frame::default()
        }
    }

    /// A road 10 m wide along x through the origin.
    fn road() -> Drivable {
        Drivable::new(&RoadNetwork {
            lanes: vec![vec![[-100.0, -5.0], [100.0, -5.0], [100.0, 5.0], [-100.0, 5.0]]],
            ..RoadNetwork::default()
        })
    }

    #[test]
    fn entries_exits_collisions_angles_and_accelerations() {
        use std::f64::consts::FRAC_PI_2;
        let road = road();
        // Frame 1: agents 1 (moving along +x, heading along it), 2 (a pedestrian standing off the road at
        // y = 20).
        let walker = Agent {
            category: AgentCategory::Pedestrian,
            ..agent(2, 0.0, 20.0, 0.0, 0.0, 1.0)
        };
        let f1 = frame(0.0, vec![agent(1, 10.0, 0.0, 10.0, 0.0, 0.0), walker]);
        // Frame 2, 0.5 s later, the ego turned left by 90°: agent 1 is now at ego (0, -10)... with the same
        // global velocity (+x) plus 1 m/s of +y: in the turned ego frame (-)x-global is -y-ego. Agent 2
        // left; agents 3 and 4 entered and overlap; agent 3 drives 30° off its heading.
        let a1 = agent(1, 0.0, -15.0, 1.0, -10.0, -FRAC_PI_2);
        let f2 = frame(
            FRAC_PI_2,
            vec![
                a1,
                agent(3, 30.0, 0.0, 5.0, 0.0, 30f64.to_radians()),
                agent(4, 31.0, 0.0, 0.0, 0.0, 0.0),
            ],
        );
        let mut s = SceneStats::default();
        s.add(&f1, None, 0.5, Some(&road));
        s.add(&f2, Some(&f1), 0.5, Some(&road));
        let r = s.summary();
        assert_eq!(r.frames, 2);
        assert_eq!(r.agents_mean, Some(2.5));
        assert_eq!(r.agents_distribution, vec![0.0, 0.0, 0.5, 0.5]);
        assert_eq!(
            (r.entries_per_s, r.exits_per_s),
            (Some(4.0), Some(2.0)),
            "2 in and 1 out in 0.5 s"
        );
        // Frame 2: agents 3 and 4 overlap (2 of 3); frame 1: none.
        assert_eq!(r.collision_rate, Some((0.0 + 2.0 / 3.0) / 2.0));
        // They entered together, so no collision began between two frames of both.
        assert_eq!(
            (r.collision_onsets_per_s, r.onsets_into_standing),
            (Some(0.0), None)
        );
        // Off road: agent 2 (y = 20); in frame 2 the ego looks along +y, so ego (30, 0) is global (0, 30)
        // and (31, 0) is (0, 31): off; ego (0, -15) is global (15, 0): on.
        assert_eq!(r.off_road_rate, Some(3.0 / 5.0));
        // Vehicles alone: agents 3 and 4 of the 4 vehicles (the pedestrian left out).
        assert_eq!(r.vehicle_off_road_rate, Some(2.0 / 4.0));
        // Entering vehicles: agents 3 and 4 of frame 2, both off.
        assert_eq!(r.entering_off_road_rate, Some(1.0));
        // Both egos stand at the origin, on the road; one moved to y = 50 is off it.
        assert_eq!(r.ego_off_road_rate, Some(0.0));
        let mut off = f1.clone();
        off.ego.y = 50.0;
        s.add(&off, None, 0.5, Some(&road));
        assert_eq!(s.summary().ego_off_road_rate, Some(1.0 / 3.0));
        // Moving agents: 1 twice (0° and atan(1/10) ≈ 5.71° off), 3 (30°).
        let m = r.heading_motion_median_deg.unwrap();
        assert!((m - (1.0f64 / 10.0).atan().to_degrees()).abs() < 1e-9, "{m}");
        // Agent 1's global velocity went from (10, 0) to (10, 1): 1 m/s in 0.5 s.
        let a = r.acceleration.unwrap();
        assert!((a.mean - 2.0).abs() < 1e-9 && a.p10 == a.p90, "{a:?}");
        // Speeds 10, 0, √101, 5, 0: the 90th percentile lies 0.6 of the way from 10 to √101.
        let p90 = r.speed.unwrap().p90;
        assert!(
            (p90 - (10.0 + 0.6 * (101f64.sqrt() - 10.0))).abs() < 1e-12,
            "{p90}"
        );
        // Agents 3 (5 m/s) and 4 (standing) entered in frame 2.
        let e = r.entry_speed.unwrap();
        assert_eq!((e.mean, e.p50, e.p90), (2.5, 2.5, 4.5));
    }

    #[test]
    fn where_vehicles_enter() {
        let road = road();
        let walker = |id, y| Agent {
            category: AgentCategory::Pedestrian,
            ..agent(id, 0.0, y, 0.0, 0.0, 0.0)
        };
        // Vehicle 1 stays on the road and walker 2 beside it; then vehicle 3 enters on the road, vehicle 4
        // and walker 5 beside it, and vehicle 1 leaves the road.
        let f1 = frame(0.0, vec![agent(1, 0.0, 0.0, 0.0, 0.0, 0.0), walker(2, 8.0)]);
        let f2 = frame(
            0.0,
            vec![
                agent(1, 0.0, 7.0, 0.0, 0.0, 0.0),
                walker(2, 8.0),
                agent(3, 20.0, 0.0, 0.0, 0.0, 0.0),
                agent(4, 40.0, 9.0, 0.0, 0.0, 0.0),
                walker(5, -9.0),
            ],
        );
        let mut s = SceneStats::default();
        s.add(&f1, None, 0.5, Some(&road));
        s.add(&f2, Some(&f1), 0.5, Some(&road));
        let r = s.summary();
        assert_eq!(
            r.entering_off_road_rate,
            Some(1.0 / 2.0),
            "vehicle 4 of vehicles 3 and 4"
        );
        assert_eq!(
            r.vehicle_off_road_rate,
            Some(2.0 / 4.0),
            "vehicle 1 in frame 2 and vehicle 4"
        );
        assert_eq!(r.off_road_rate, Some(5.0 / 7.0));
        // Without a map, nothing is known of the road.
        let mut blind = SceneStats::default();
        blind.add(&f1, None, 0.5, None);
        blind.add(&f2, Some(&f1), 0.5, None);
        assert_eq!(blind.summary().entering_off_road_rate, None);
    }

    #[test]
    fn seconds_of_the_horizon() {
        let s: Vec<usize> = (1..=5).map(|h| second_of(h, 0.5)).collect();
        assert_eq!(s, [1, 1, 2, 2, 3]);
        assert_eq!(second_of(1, 0.1), 1);
        assert_eq!(second_of(10, 0.1), 1);
        assert_eq!(second_of(11, 0.1), 2);
    }
}
