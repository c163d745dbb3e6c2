//! Scene statistics over a rollout's horizon, in the same terms for generated rollouts and real clips:
//! agents per frame (mean and distribution), agents entering and leaving per second, the collision and
//! off-road rates, the collisions that begin (and how many of them at speed into a standing agent), how
//! far moving agents' headings are from their direction of motion, the speed and acceleration
//! distributions, how fast agents are when they enter, how often they brake on the approach to a
//! standing agent ([`crate::approach`]), how soon standing agents drive off and how vehicles leave the
//! road ([`crate::leaving`]). [`SceneStats`] gathers them frame
//! by frame, each frame with the one before it in its sequence (entries, exits and accelerations need
//! both); [`SceneStats::summary`] reports them.

use crate::approach::{ApproachRule, Approaches, approaches};
use crate::collision::{colliding, collision_onsets, overlapping_ego};
use crate::counts::rate_95;
use crate::l2::{global_position, global_velocity, median, quantile};
use crate::leaving::{Leaving, LeavingCounts};
use crate::offroad::Drivable;
use serde::Serialize;
use std::collections::{HashMap, HashSet};
use umgen_scene::{Agent, AgentCategory, EgoPose, Frame, wrap_angle};

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
    /// The x and y range (m, ego frame) agents can be placed in ([`SceneStats::within`]), and the entries
    /// and exits inside it: agents that appear or vanish where they could have been seen a step before or
    /// after.
    extent: Option<[[f64; 2]; 2]>,
    entries_inside: usize,
    exits_inside: usize,
    /// Seconds between the frames of the transitions.
    seconds: f64,
    /// Per frame with agents, the fraction that overlaps another.
    collision_rates: Vec<f64>,
    /// The ego's box (length, width in m) to test agents against, frames tested and those where an agent
    /// overlaps it.
    ego_box: Option<[f64; 2]>,
    ego_frames: usize,
    ego_hit_frames: usize,
    /// Collisions begun between consecutive frames, and those driven at speed into a standing agent.
    onsets: usize,
    onsets_standing: usize,
    /// Approaches at speed to a standing agent ahead, and those that braked.
    approaches: Approaches,
    /// Agents standing in a frame and present in the next, and those moving in the next.
    standing: usize,
    starts: usize,
    /// Agents tested against a map, and those off its drivable area.
    on_map: usize,
    off_road: usize,
    /// The same for vehicles alone: pedestrians walk off the drivable area, vehicles do not.
    vehicles_on_map: usize,
    vehicles_off_road: usize,
    /// The same for the vehicles of frames whose ego is on the drivable area.
    vehicles_on_map_ego_on: usize,
    vehicles_off_road_ego_on: usize,
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
    /// Vehicles on the drivable area in one frame and off it in the next.
    leaving: Leaving,
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

/// Events counted between consecutive frames, over `seconds`, with the 95 % interval of each one's rate
/// per second ([`crate::counts::rate_95`]: the count taken as Poisson; events of one scene are not
/// independent, so the true uncertainty is if anything wider).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EventCounts {
    /// Seconds between the frames of the transitions counted.
    pub seconds: f64,
    /// Agents entering.
    pub entries: usize,
    /// Agents leaving.
    pub exits: usize,
    /// Collisions begun.
    pub onsets: usize,
    /// Of the entries, those inside the agents' range ([`SceneStats::within`]): the agent's position a
    /// step before, at its velocity, lies in the range of the frame before, where it was not. `None`
    /// without a range.
    pub entries_inside: Option<usize>,
    /// Of the exits, those inside the range: the agent's position a step after, at its velocity, lies in
    /// the range of the next frame, where it is not.
    pub exits_inside: Option<usize>,
    /// 95 % interval of the entries per second; `None` without time.
    pub entries_per_s_95: Option<[f64; 2]>,
    /// 95 % interval of the exits per second.
    pub exits_per_s_95: Option<[f64; 2]>,
    /// 95 % interval of the collisions begun per second.
    pub onsets_per_s_95: Option<[f64; 2]>,
    /// Vehicles leaving the road ([`crate::leaving`]); `None` without maps.
    pub leaving_road: Option<LeavingCounts>,
}

impl EventCounts {
    fn of(s: &SceneStats) -> Self {
        let (seconds, entries, exits, onsets) = (s.seconds, s.entries, s.exits, s.onsets);
        let rate = |k| rate_95(k, seconds);
        let inside = |k| s.extent.map(|_| k);
        Self {
            seconds,
            entries,
            exits,
            onsets,
            entries_inside: inside(s.entries_inside),
            exits_inside: inside(s.exits_inside),
            entries_per_s_95: rate(entries),
            exits_per_s_95: rate(exits),
            onsets_per_s_95: rate(onsets),
            leaving_road: (s.ego_on_map > 0).then(|| s.leaving.counts(seconds)),
        }
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
    /// The events behind the rates per second, and the seconds they were counted over: agents entering
    /// and leaving, collisions begun.
    pub counts: EventCounts,
    /// Mean over frames with agents of the fraction that overlaps another (the authors' ratio).
    pub collision_rate: Option<f64>,
    /// Fraction of frames in which an agent overlaps the ego's box; `None` without a box
    /// ([`SceneStats::with_ego_box`]).
    pub ego_overlap_rate: Option<f64>,
    /// Collisions begun per second: pairs of agents whose boxes overlap in a frame and did not in the
    /// one before.
    pub collision_onsets_per_s: Option<f64>,
    /// Of those, the fraction driven at speed into a standing agent
    /// ([`crate::collision::INTO_STANDING_M_S`]: one below [`MOVING_M_S`], the other above 5 m/s before
    /// the step). `None` without onsets.
    pub onsets_into_standing: Option<f64>,
    /// Approaches per second: agents driving at speed towards a standing agent ahead in their lane
    /// ([`ApproachRule`]'s defaults: above 5 m/s, less than 3 s away).
    pub approaches_per_s: Option<f64>,
    /// Of those, the fraction that slowed by at least 1 m/s² by the next frame. `None` without approaches.
    pub approach_braking: Option<f64>,
    /// The same fraction of the approaches whose agent had not braked over the step before
    /// ([`Approaches::unbraked`]): braking that begins, not braking carried on. `None` without them.
    pub approach_braking_onset: Option<f64>,
    /// Of the agents standing in a frame (below [`MOVING_M_S`]) and present in the next, the fraction
    /// moving there (above it), per second: how soon a standing agent drives off. `None` without any.
    pub starts_per_standing_s: Option<f64>,
    /// Fraction of agents whose centre is off the drivable area (lanes, connectors, intersections) of
    /// the scene's map; `None` without maps.
    pub off_road_rate: Option<f64>,
    /// The same for vehicles alone (pedestrians walk beside the roads, so a change of the pedestrian
    /// share moves `off_road_rate` without any vehicle leaving the road); `None` without maps.
    pub vehicle_off_road_rate: Option<f64>,
    /// `vehicle_off_road_rate` over the frames whose ego is on the drivable area: the vehicles that leave
    /// the road themselves, not carried off it by an ego that left it. `None` without such frames.
    pub vehicle_off_road_ego_on_rate: Option<f64>,
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
    /// Statistics that also count the frames in which an agent overlaps the ego's box `ego` (length, width
    /// in m, centred at the ego pose along its heading).
    pub fn with_ego_box(ego: [f64; 2]) -> Self {
        Self {
            ego_box: Some(ego),
            ..Self::default()
        }
    }

    /// Statistics that also tell the agents entering and leaving inside the range they can be placed in
    /// (`x` and `y`, m, in the ego frame: the agent modality's) from those crossing its edge.
    pub fn within(self, x: [f64; 2], y: [f64; 2]) -> Self {
        Self {
            extent: Some([x, y]),
            ..self
        }
    }

    /// Whether agent `a` of the frame whose ego is `ego`, moved `dt` seconds at its velocity (back in time
    /// where `dt` is negative), lies in the range of the frame whose ego is `other`.
    fn inside(&self, a: &Agent, ego: &EgoPose, dt: f64, other: &EgoPose) -> bool {
        self.extent.is_some_and(|[x, y]| {
            let (g, v) = (global_position(ego, a), global_velocity(ego, a));
            let p = other.pose2().to_local([g[0] + v[0] * dt, g[1] + v[1] * dt]);
            (x[0]..=x[1]).contains(&p[0]) && (y[0]..=y[1]).contains(&p[1])
        })
    }

    /// Adds `frame`, with the frames before it in its sequence (`dt` seconds apart, the last one just
    /// before it; empty at a sequence's start) and the drivable area of its map, if known.
    pub fn add(&mut self, frame: &Frame, before: &[Frame], dt: f64, drivable: Option<&Drivable>) {
        let agents = &frame.agents;
        self.counts.push(agents.len());
        let ego_on = drivable.map(|d| d.contains([frame.ego.x, frame.ego.y]));
        if let Some(on) = ego_on {
            self.ego_on_map += 1;
            self.ego_off_road += usize::from(!on);
        }
        if let Some(d) = drivable {
            self.leaving.add(frame, before, d);
        }
        if !agents.is_empty() {
            let (hit, n) = colliding(agents);
            self.collision_rates.push(hit as f64 / n as f64);
        }
        if let Some(ego) = self.ego_box {
            self.ego_frames += 1;
            self.ego_hit_frames += usize::from(overlapping_ego(agents, ego) > 0);
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
                    if ego_on == Some(true) {
                        self.vehicles_on_map_ego_on += 1;
                        self.vehicles_off_road_ego_on += usize::from(off);
                    }
                }
            }
            vehicle_off.push(off.filter(|_| vehicle));
        }
        let Some((before, earlier_frames)) = before.split_last() else {
            return;
        };
        let earlier: HashMap<u64, [f64; 2]> = before
            .agents
            .iter()
            .map(|a| (a.track_id, global_velocity(&before.ego, a)))
            .collect();
        let moving = |v: [f64; 2]| v[0].hypot(v[1]) > MOVING_M_S;
        let mut stayed = 0;
        for (a, off) in agents.iter().zip(vehicle_off) {
            if let Some(v0) = earlier.get(&a.track_id) {
                stayed += 1;
                let v1 = global_velocity(&frame.ego, a);
                self.accelerations.push((v1[0] - v0[0]).hypot(v1[1] - v0[1]) / dt);
                if !moving(*v0) {
                    self.standing += 1;
                    self.starts += usize::from(moving(v1));
                }
            } else {
                self.entry_speeds.push(a.vx.hypot(a.vy));
                self.entries_inside += usize::from(self.inside(a, &frame.ego, -dt, &before.ego));
                if let Some(off) = off {
                    self.entering_on_map += 1;
                    self.entering_off_road += usize::from(off);
                }
            }
        }
        if self.extent.is_some() {
            let now: HashSet<u64> = agents.iter().map(|a| a.track_id).collect();
            for b in before.agents.iter().filter(|b| !now.contains(&b.track_id)) {
                self.exits_inside += usize::from(self.inside(b, &before.ego, dt, &frame.ego));
            }
        }
        let (onsets, standing) = collision_onsets(&before.agents, agents);
        self.onsets += onsets;
        self.onsets_standing += standing;
        let earliest = earlier_frames.last().map(|f| f.agents.as_slice());
        self.approaches += approaches(&ApproachRule::default(), earliest, &before.agents, agents, dt);
        self.transitions += 1;
        self.seconds += dt;
        self.entries += agents.len() - stayed;
        self.exits += before.agents.len() - stayed;
    }

    /// Mean seconds between the frames of the transitions.
    fn step_s(&self) -> f64 {
        self.seconds / self.transitions.max(1) as f64
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
            counts: EventCounts::of(self),
            collision_rate: mean(&self.collision_rates),
            ego_overlap_rate: share(self.ego_hit_frames, self.ego_frames),
            collision_onsets_per_s: per_s(self.onsets),
            onsets_into_standing: share(self.onsets_standing, self.onsets),
            approaches_per_s: per_s(self.approaches.seen),
            approach_braking: share(self.approaches.braked, self.approaches.seen),
            approach_braking_onset: share(self.approaches.unbraked_braked, self.approaches.unbraked),
            starts_per_standing_s: share(self.starts, self.standing).map(|f| f / self.step_s()),
            off_road_rate: share(self.off_road, self.on_map),
            vehicle_off_road_rate: share(self.vehicles_off_road, self.vehicles_on_map),
            vehicle_off_road_ego_on_rate: share(self.vehicles_off_road_ego_on, self.vehicles_on_map_ego_on),
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
mod tests;
