//! Braking for a standing agent ahead: of the agents driving at speed towards a standing agent in their
//! lane, how many slow down by the next frame. A generator whose agents keep their speed into a queue or
//! a red light's stop line collides where the real traffic brakes; the collision rate shows the outcome,
//! this shows the missing response frames before it, on real clips and generated rollouts alike.

use crate::collision::INTO_STANDING_M_S;
use std::collections::HashMap;
use umgen_scene::{Agent, wrap_angle};

/// What counts as an approach and as braking.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ApproachRule {
    /// The approaching agent is faster than this (m/s); the one ahead slower than the first of
    /// [`INTO_STANDING_M_S`].
    pub fast_m_s: f64,
    /// Most lateral offset (m) of the standing agent's centre from the approaching agent's axis: the
    /// same lane (SUMO's lanes are 3.2 m wide).
    pub lane_half_width_m: f64,
    /// Most difference (degrees) between the two headings: the same direction of travel.
    pub heading_deg: f64,
    /// Most time (s) to reach the standing agent's rear at the approaching agent's speed.
    pub time_gap_s: f64,
    /// Least deceleration (m/s²) over the step that counts as braking.
    pub braking_m_s2: f64,
}

impl Default for ApproachRule {
    /// Closing at above 5 m/s on a standing agent less than 3 s ahead: a vehicle of SUMO's car-following
    /// model (4.5 m/s² of comfortable deceleration) needs 2.8 s to stop from 12.5 m/s, so it is braking
    /// there. Braking is 1 m/s² or more: twice the noise of 1,024 velocity bins over one 0.5 s step.
    fn default() -> Self {
        Self {
            fast_m_s: INTO_STANDING_M_S.1,
            lane_half_width_m: 1.5,
            heading_deg: 30.0,
            time_gap_s: 3.0,
            braking_m_s2: 1.0,
        }
    }
}

/// Approaches counted over one step, and of them those that braked.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Approaches {
    /// Approaches whose agent is still there in the next frame.
    pub seen: usize,
    /// Of those, the ones that braked over the step.
    pub braked: usize,
    /// Approaches whose agent was in the frame before as well and had not braked over that step: where
    /// braking must begin rather than carry on. A generator that continues each agent's motion brakes
    /// on the others without knowing what stands ahead.
    pub unbraked: usize,
    /// Of those, the ones that braked over the step.
    pub unbraked_braked: usize,
}

impl std::ops::AddAssign for Approaches {
    fn add_assign(&mut self, o: Self) {
        self.seen += o.seen;
        self.braked += o.braked;
        self.unbraked += o.unbraked;
        self.unbraked_braked += o.unbraked_braked;
    }
}

/// Approaches in `prev` (an agent faster than [`ApproachRule::fast_m_s`] with a standing agent ahead in
/// its lane, less than [`ApproachRule::time_gap_s`] away bumper to bumper) whose agent is still there in
/// `next`, `dt` seconds later, and of them those that braked (speed down by at least
/// [`ApproachRule::braking_m_s2`] × `dt`); `earlier`, the frame `dt` before `prev` if there is one, tells
/// which agents had not braked yet ([`Approaches::unbraked`]). Agents match by `track_id`; geometry and
/// speeds do not depend on the frame, so each frame may be in its own ego frame.
pub fn approaches(
    rule: &ApproachRule,
    earlier: Option<&[Agent]>,
    prev: &[Agent],
    next: &[Agent],
    dt: f64,
) -> Approaches {
    let by_id =
        |agents: &[Agent]| -> HashMap<u64, f64> { agents.iter().map(|a| (a.track_id, speed(a))).collect() };
    let later = by_id(next);
    let before = earlier.map(by_id).unwrap_or_default();
    let braking = |from: f64, to: f64| from - to >= rule.braking_m_s2 * dt;
    let mut out = Approaches::default();
    for a in prev {
        let v = speed(a);
        if v <= rule.fast_m_s {
            continue;
        }
        let Some(&v1) = later.get(&a.track_id) else {
            continue;
        };
        let (c, s) = (a.heading.cos(), a.heading.sin());
        let ahead = prev.iter().any(|b| {
            if b.track_id == a.track_id || speed(b) >= INTO_STANDING_M_S.0 {
                return false;
            }
            let (dx, dy) = (b.x - a.x, b.y - a.y);
            let (along, across) = (dx * c + dy * s, -dx * s + dy * c);
            let gap = along - (a.length + b.length) / 2.0;
            along > 0.0
                && across.abs() <= rule.lane_half_width_m
                && wrap_angle(b.heading - a.heading).abs().to_degrees() <= rule.heading_deg
                && gap <= v * rule.time_gap_s
        });
        if !ahead {
            continue;
        }
        let braked = usize::from(braking(v, v1));
        out.seen += 1;
        out.braked += braked;
        if before.get(&a.track_id).is_some_and(|&v0| !braking(v0, v)) {
            out.unbraked += 1;
            out.unbraked_braked += braked;
        }
    }
    out
}

fn speed(a: &Agent) -> f64 {
    a.vx.hypot(a.vy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::collision::bev_box;

    fn car(id: u64, x: f64, y: f64, heading: f64, speed: f64) -> Agent {
        Agent {
            track_id: id,
            vx: speed * heading.cos(),
            vy: speed * heading.sin(),
            ..bev_box(x, y, heading, 4.0, 2.0)
        }
    }

    /// Approaches without a frame before them: none counts as unbraked.
    fn counts(seen: usize, braked: usize) -> Approaches {
        Approaches {
            seen,
            braked,
            ..Approaches::default()
        }
    }

    #[test]
    fn approaches_are_counted_and_braking_is_read_from_the_speed() {
        let rule = ApproachRule::default();
        let up = std::f64::consts::FRAC_PI_2;
        // Along +y: 1 at 10 m/s with 2 standing 20 m ahead (16 m bumper to bumper, under 30 m);
        // 3 at 10 m/s with 4 standing 40 m ahead (36 m: too far); 5 at 10 m/s with 6 standing 20 m
        // ahead but 2 m aside (another lane); 7 at 10 m/s with 8 standing 20 m ahead facing the other
        // way; 9 at 4 m/s (not fast) with 10 standing 8 m ahead; 11 at 10 m/s with 12 standing behind.
        let prev = vec![
            car(1, 0.0, 0.0, up, 10.0),
            car(2, 0.0, 20.0, up, 0.0),
            car(3, 10.0, 0.0, up, 10.0),
            car(4, 10.0, 40.0, up, 0.0),
            car(5, 20.0, 0.0, up, 10.0),
            car(6, 22.0, 20.0, up, 0.0),
            car(7, 30.0, 0.0, up, 10.0),
            car(8, 30.0, 20.0, -up, 0.0),
            car(9, 40.0, 0.0, up, 4.0),
            car(10, 40.0, 8.0, up, 0.0),
            car(11, 50.0, 0.0, up, 10.0),
            car(12, 50.0, -20.0, up, 0.0),
        ];
        // Half a second later 1 is down to 9.4 m/s (1.2 m/s²): braked.
        let mut next = prev.clone();
        next[0] = car(1, 0.0, 4.9, up, 9.4);
        assert_eq!(approaches(&rule, None, &prev, &next, 0.5), counts(1, 1));
        // Down to 9.6 m/s only (0.8 m/s²): an approach without braking; gone: no approach.
        next[0] = car(1, 0.0, 5.0, up, 9.6);
        assert_eq!(approaches(&rule, None, &prev, &next, 0.5), counts(1, 0));
        assert_eq!(approaches(&rule, None, &prev, &next[1..], 0.5), counts(0, 0));
        // Rotated by 1 rad about the origin, the same scene holds the same approach.
        let turn = |a: &Agent| {
            let (c, s) = (1f64.cos(), 1f64.sin());
            Agent {
                x: a.x * c - a.y * s,
                y: a.x * s + a.y * c,
                vx: a.vx * c - a.vy * s,
                vy: a.vx * s + a.vy * c,
                heading: a.heading + 1.0,
                ..*a
            }
        };
        let (p2, n2): (Vec<Agent>, Vec<Agent>) =
            (prev.iter().map(turn).collect(), next.iter().map(turn).collect());
        assert_eq!(approaches(&rule, None, &p2, &n2, 0.5), counts(1, 0));
        // At 20 m/s the 40 m of agent 3 are within 3 s as well.
        let mut fast = prev.clone();
        fast[2] = car(3, 10.0, 0.0, up, 20.0);
        assert_eq!(approaches(&rule, None, &fast, &fast, 0.5), counts(2, 0));
    }

    #[test]
    fn unbraked_approaches_are_those_whose_agent_kept_its_speed_the_step_before() {
        let rule = ApproachRule::default();
        let up = std::f64::consts::FRAC_PI_2;
        // Two lanes along +y, each with a car 20 m behind a standing one. Half a second before, car 1
        // drove at 10.2 m/s (0.4 m/s² down to 10: not braking) and car 3 at 11 m/s (2 m/s²: braking);
        // car 5, a third approach, was not there.
        let prev = vec![
            car(1, 0.0, 0.0, up, 10.0),
            car(2, 0.0, 20.0, up, 0.0),
            car(3, 10.0, 0.0, up, 10.0),
            car(4, 10.0, 20.0, up, 0.0),
            car(5, 20.0, 0.0, up, 10.0),
            car(6, 20.0, 20.0, up, 0.0),
        ];
        let earlier = vec![car(1, 0.0, -5.0, up, 10.2), car(3, 10.0, -5.0, up, 11.0)];
        // Next, car 1 brakes (9 m/s) and cars 3 and 5 keep 10 m/s.
        let mut next = prev.clone();
        next[0] = car(1, 0.0, 4.8, up, 9.0);
        let got = approaches(&rule, Some(&earlier), &prev, &next, 0.5);
        let want = Approaches {
            seen: 3,
            braked: 1,
            unbraked: 1,
            unbraked_braked: 1,
        };
        assert_eq!(got, want);
        // Car 1 keeps its speed instead: still unbraked, now without braking.
        next[0] = car(1, 0.0, 5.0, up, 10.0);
        let got = approaches(&rule, Some(&earlier), &prev, &next, 0.5);
        assert_eq!((got.unbraked, got.unbraked_braked, got.braked), (1, 0, 0));
    }
}
