//! Stop-line crossings: how often vehicles cross a stop line while its light is red. It measures whether
//! agents, recorded or generated, obey the lights (`examples/red-light.rs` runs it over a split and over
//! `umgen generate` outputs).

use crate::modality::Head;
use serde::Serialize;
use umgen::data::LightState;
use umgen::scene::{AgentCategory, Frame, Pose2, wrap_angle};

/// Heads closer than this (m) with headings within [`SAME_HEADING`] stand at one stop line.
const SAME_LINE_M: f64 = 1.0;
/// Headings (rad) of heads at one stop line.
const SAME_HEADING: f64 = 0.3;
/// How far (m) beside a head a vehicle's centre may cross its line: half a lane.
pub const HALF_LANE_M: f64 = 1.75;
/// A vehicle farther behind a line than this (m) before the step did not cross it in one step.
pub const MAX_APPROACH_M: f64 = 20.0;
/// A vehicle crossing a red line faster than this (m/s, before the step) had not braked for it: it
/// drove through, where a slower one may have crept over the line while stopping.
pub const THROUGH_MPS: f64 = 5.0;

/// One stop line in world coordinates and the state it shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StopLine {
    /// Where the heads stand (m, world).
    pub at: [f64; 2],
    /// Direction of travel (rad, world).
    pub heading: f64,
    /// Green if any head at the line is green, else yellow if any is yellow, else red if any is red:
    /// a vehicle crossing on red crossed where no movement had green or yellow.
    pub state: LightState,
}

impl StopLine {
    /// Whether `other` stands within `within_m` of this line and faces its way (within
    /// [`SAME_HEADING`]).
    fn near(&self, other: &StopLine, within_m: f64) -> bool {
        (self.at[0] - other.at[0]).hypot(self.at[1] - other.at[1]) < within_m
            && wrap_angle(self.heading - other.heading).abs() < SAME_HEADING
    }

    /// `p` (world) in the line's frame: along the direction of travel (negative before the line) and
    /// beside it (left positive).
    fn local(&self, p: [f64; 2]) -> [f64; 2] {
        Pose2::new(self.at[0], self.at[1], self.heading).to_local(p)
    }
}

/// The stop lines of a frame's heads (given in the frame of `ego`), heads at one line merged.
pub fn stop_lines(heads: &[Head], ego: &Pose2) -> Vec<StopLine> {
    let mut lines: Vec<StopLine> = Vec::new();
    for h in heads {
        let line = StopLine {
            at: ego.to_parent([h.x, h.y]),
            heading: wrap_angle(h.heading + ego.heading),
            state: h.state,
        };
        match lines.iter_mut().find(|l| l.near(&line, SAME_LINE_M)) {
            Some(l) => l.state = merge(l.state, h.state),
            None => lines.push(line),
        }
    }
    lines
}

fn merge(a: LightState, b: LightState) -> LightState {
    let rank = |s: LightState| match s {
        LightState::Off => 0,
        LightState::Red => 1,
        LightState::Yellow => 2,
        LightState::Green => 3,
    };
    if rank(b) > rank(a) { b } else { a }
}

/// Stop-line crossings, counted by the state of the line crossed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct Crossings {
    /// Lines whose heads were dark or unknown.
    pub off: u64,
    /// Lines showing red.
    pub red: u64,
    /// Of `red`, those whose vehicle moved faster than [`THROUGH_MPS`] before the step.
    pub red_through: u64,
    /// Lines showing yellow.
    pub yellow: u64,
    /// Lines showing green.
    pub green: u64,
    /// Vehicles before a step within [`MAX_APPROACH_M`] behind a red line and [`HALF_LANE_M`] beside it
    /// (one per vehicle and line): the chances to run a red light.
    pub red_approaches: u64,
}

impl Crossings {
    /// Every crossing.
    pub fn total(&self) -> u64 {
        self.off + self.red + self.yellow + self.green
    }

    /// The share of crossings made on red, if there were any.
    pub fn red_share(&self) -> Option<f64> {
        let t = self.total();
        (t > 0).then(|| self.red as f64 / t as f64)
    }

    /// The 95 % Wilson score interval of [`red_share`](Self::red_share): how far apart two rollouts'
    /// shares must be before their difference is more than the draw of their crossings.
    pub fn red_share_interval(&self) -> Option<(f64, f64)> {
        let n = self.total();
        (n > 0).then(|| {
            let (n, z) = (n as f64, 1.959_963_984_540_054_f64);
            let p = self.red as f64 / n;
            let centre = (p + z * z / (2.0 * n)) / (1.0 + z * z / n);
            let half = z / (1.0 + z * z / n) * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt();
            (centre - half, centre + half)
        })
    }

    /// Red crossings per red approach: how often a vehicle near a red line ran it in the next step.
    pub fn run_rate(&self) -> Option<f64> {
        (self.red_approaches > 0).then(|| self.red as f64 / self.red_approaches as f64)
    }

    /// Adds another count.
    pub fn add(&mut self, o: &Crossings) {
        self.red_approaches += o.red_approaches;
        self.off += o.off;
        self.red += o.red;
        self.red_through += o.red_through;
        self.yellow += o.yellow;
        self.green += o.green;
    }

    fn count(&mut self, s: LightState) {
        match s {
            LightState::Off => self.off += 1,
            LightState::Red => self.red += 1,
            LightState::Yellow => self.yellow += 1,
            LightState::Green => self.green += 1,
        }
    }
}

/// The crossings from `prev` to `next` (consecutive frames): each vehicle in both (one track id) whose
/// centre goes from behind a line of `lines` (the lines at `prev`, in world coordinates) to on or past
/// it, within [`HALF_LANE_M`] of the heads where it crosses, counted under the line's state; and the red
/// approaches before the step. Agent positions are in each frame's own ego frame (`Frame::ego`); the
/// speeds of red crossings are the vehicles' own velocities in `prev`.
pub fn crossings(prev: &Frame, next: &Frame, lines: &[StopLine]) -> Crossings {
    let (p_ego, n_ego) = (prev.ego.pose2(), next.ego.pose2());
    let mut out = Crossings::default();
    for a in prev
        .agents
        .iter()
        .filter(|a| a.category == AgentCategory::Vehicle)
    {
        let Some(b) = next.agents.iter().find(|b| b.track_id == a.track_id) else {
            continue;
        };
        let (p0, p1) = (p_ego.to_parent([a.x, a.y]), n_ego.to_parent([b.x, b.y]));
        for l in lines {
            let ([s0, d0], [s1, d1]) = (l.local(p0), l.local(p1));
            if !(s0 < 0.0 && s0 > -MAX_APPROACH_M) {
                continue;
            }
            if l.state == LightState::Red && d0.abs() <= HALF_LANE_M {
                out.red_approaches += 1;
            }
            if s1 < 0.0 {
                continue;
            }
            // Beside the line where the straight path between the two positions meets it.
            let f = -s0 / (s1 - s0);
            if (d0 + f * (d1 - d0)).abs() <= HALF_LANE_M {
                out.count(l.state);
                if l.state == LightState::Red && a.vx.hypot(a.vy) > THROUGH_MPS {
                    out.red_through += 1;
                }
            }
        }
    }
    out
}

/// How a scene's own lights agree with recorded ones: of the recorded stop lines, how many have a
/// generated line within [`SAME_LINE_M`] · 2 and [`SAME_HEADING`], and how many of those show the
/// recorded state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct Agreement {
    /// Recorded stop lines.
    pub lines: u64,
    /// Those with a generated line at their place.
    pub matched: u64,
    /// Those matched lines whose generated state is the recorded one.
    pub same_state: u64,
}

impl Agreement {
    /// Compares the generated lines of one frame with the recorded ones of the same time.
    pub fn add(&mut self, recorded: &[StopLine], generated: &[StopLine]) {
        for r in recorded {
            self.lines += 1;
            if let Some(g) = generated.iter().find(|g| r.near(g, 2.0 * SAME_LINE_M)) {
                self.matched += 1;
                self.same_state += u64::from(g.state == r.state);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use umgen::scene::{Agent, EgoPose};

    fn head(x: f64, y: f64, heading: f64, state: LightState) -> Head {
        Head { x, y, heading, state }
    }

    fn frame(ego_x: f64, agents: &[(u64, AgentCategory, f64, f64)]) -> Frame {
        Frame {
            ego: EgoPose {
                x: ego_x,
                ..EgoPose::default()
            },
            agents: agents
                .iter()
                .map(|&(track_id, category, x, y)| Agent {
                    track_id,
                    category,
                    x,
                    y,
                    z: 0.0,
                    vx: 0.0,
                    vy: 0.0,
                    vz: 0.0,
                    heading: 0.0,
                    length: 4.5,
                    width: 1.9,
                    height: 1.5,
                })
                .collect(),
            ..Frame::default()
        }
    }

    #[test]
    fn crossings_are_counted_in_world_coordinates_by_the_lines_state() {
        // The ego at x = 0 sees a red line 10 m ahead (heading east) and a green one 10 m behind it.
        let lines = stop_lines(
            &[
                head(10.0, 0.0, 0.0, LightState::Red),
                head(-10.0, 0.5, 0.0, LightState::Green),
            ],
            &Pose2::new(0.0, 0.0, 0.0),
        );
        assert_eq!(lines.len(), 2);
        let v = AgentCategory::Vehicle;
        // Ego moves 5 m, so positions in the next frame are 5 m smaller.
        let prev = frame(
            0.0,
            &[
                (1, v, 8.0, 1.0),                         // crosses the red line 1 m beside its head
                (2, v, 8.0, 3.0),                         // beside the lane: no crossing, no approach
                (3, v, -12.0, 0.0),                       // crosses the green line
                (4, AgentCategory::Pedestrian, 8.0, 0.0), // not a vehicle
                (5, v, 9.0, -1.0),                        // waits at the red line
                (6, v, 12.0, 0.0),                        // already past it
                (7, v, 9.5, 0.0),                         // gone in the next frame
            ],
        );
        let next = frame(
            5.0,
            &[
                (1, v, 6.0, 1.0),
                (2, v, 6.0, 3.0),
                (3, v, -14.0, 0.0),
                (4, AgentCategory::Pedestrian, 6.0, 0.0),
                (5, v, 4.0, -1.0),
                (6, v, 10.0, 0.0),
            ],
        );
        let c = crossings(&prev, &next, &lines);
        assert_eq!(
            c,
            Crossings {
                off: 0,
                red: 1,
                red_through: 0,
                yellow: 0,
                green: 1,
                red_approaches: 2
            }
        );
        assert_eq!(c.red_share(), Some(0.5));
        assert_eq!(c.run_rate(), Some(0.5));
        // Wilson intervals (z = 1.96) worked out by hand: 28 of 98, and 0 of 10, whose lower end is 0.
        let share = |red, green| Crossings { red, green, ..c }.red_share_interval().unwrap();
        let (lo, hi) = share(28, 70);
        assert!(
            (lo - 0.205_688).abs() < 1e-6 && (hi - 0.381_907).abs() < 1e-6,
            "{lo} {hi}"
        );
        let (lo, hi) = share(0, 10);
        assert!(lo.abs() < 1e-12 && (hi - 0.277_533).abs() < 1e-6, "{lo} {hi}");
        assert_eq!(Crossings::default().red_share_interval(), None);
        // The vehicle's own velocity before the step decides: 6 m/s drove through, 4.9 m/s did not.
        let mut fast = prev.clone();
        fast.agents[0].vx = 6.0;
        let mut slow = prev.clone();
        slow.agents[0].vy = 4.9;
        assert_eq!(crossings(&fast, &next, &lines).red_through, 1);
        assert_eq!(crossings(&slow, &next, &lines).red_through, 0);
    }

    #[test]
    fn heads_at_one_line_show_its_most_permissive_state() {
        let ego = Pose2::new(100.0, 50.0, std::f64::consts::FRAC_PI_2);
        let lines = stop_lines(
            &[
                head(10.0, 0.0, 0.0, LightState::Red),
                head(10.3, 0.2, 0.05, LightState::Green),
                head(10.0, 0.0, 3.0, LightState::Red),
            ],
            &ego,
        );
        // The third faces the other way: a line of its own.
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[0].state, LightState::Green);
        // 10 m ahead of an ego facing north is 10 m north of it.
        assert!((lines[0].at[0] - 100.0).abs() < 1e-9 && (lines[0].at[1] - 60.0).abs() < 1e-9);
        assert!((lines[0].heading - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
        assert_eq!(lines[1].state, LightState::Red);
        assert_eq!(Crossings::default().red_share(), None);
    }

    #[test]
    fn agreement_matches_lines_by_place_and_direction() {
        let ego = Pose2::new(0.0, 0.0, 0.0);
        let recorded = stop_lines(
            &[
                head(10.0, 0.0, 0.0, LightState::Red),
                head(-10.0, 5.0, 0.0, LightState::Green),
                head(20.0, 20.0, 1.0, LightState::Red),
            ],
            &ego,
        );
        // The generated ego stands 1 m further on: its lights are 1 m nearer.
        let generated = stop_lines(
            &[
                head(8.5, 0.5, 0.1, LightState::Red),         // the first, same state
                head(-11.0, 5.0, 0.0, LightState::Red),       // the second, other state
                head(19.0, 20.0, 1.0 + 3.0, LightState::Red), // the third's place, facing away
            ],
            &Pose2::new(1.0, 0.0, 0.0),
        );
        let mut a = Agreement::default();
        a.add(&recorded, &generated);
        assert_eq!(
            a,
            Agreement {
                lines: 3,
                matched: 2,
                same_state: 1
            }
        );
    }
}
