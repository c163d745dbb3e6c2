//! BEV collisions: exact overlap of rotated rectangles (separating-axis test), and the per-frame rate of
//! agents that overlap at least one other agent (the authors' `ratio`, ego not counted).

use umgen_scene::{Agent, AgentCategory};

/// A vehicle that is only a BEV box (centre, heading, length, width), for overlap tests.
pub fn bev_box(x: f64, y: f64, heading: f64, length: f64, width: f64) -> Agent {
    Agent {
        track_id: 0,
        category: AgentCategory::Vehicle,
        x,
        y,
        z: 0.0,
        vx: 0.0,
        vy: 0.0,
        vz: 0.0,
        heading,
        length,
        width,
        height: 0.0,
    }
}

/// The four corners of an agent's BEV box.
pub fn corners(a: &Agent) -> [[f64; 2]; 4] {
    let (c, s) = (a.heading.cos(), a.heading.sin());
    let (hl, hw) = (a.length / 2.0, a.width / 2.0);
    [[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]].map(|[u, v]| [a.x + u * c - v * s, a.y + u * s + v * c])
}

fn project(poly: &[[f64; 2]; 4], axis: [f64; 2]) -> (f64, f64) {
    poly.iter()
        .map(|p| p[0] * axis[0] + p[1] * axis[1])
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        })
}

/// Whether two agents' boxes overlap (touching edges count as no overlap).
pub fn overlap(a: &Agent, b: &Agent) -> bool {
    let (pa, pb) = (corners(a), corners(b));
    for poly in [&pa, &pb] {
        for i in 0..2 {
            let e = [poly[i + 1][0] - poly[i][0], poly[i + 1][1] - poly[i][1]];
            let axis = [-e[1], e[0]];
            let (a0, a1) = project(&pa, axis);
            let (b0, b1) = project(&pb, axis);
            if a1 <= b0 || b1 <= a0 {
                return false;
            }
        }
    }
    true
}

/// Agents of one frame that overlap at least one other, and the number of agents.
pub fn colliding(agents: &[Agent]) -> (usize, usize) {
    let hit = (0..agents.len())
        .filter(|&i| (0..agents.len()).any(|j| j != i && overlap(&agents[i], &agents[j])))
        .count();
    (hit, agents.len())
}

/// Agents whose box overlaps the ego's, `ego` (length, width in m) centred at the frame's origin along +x:
/// agents are placed in the ego's coordinates, and a generator that places them through the ego collides
/// where the agents-only rate does not look.
pub fn overlapping_ego(agents: &[Agent], ego: [f64; 2]) -> usize {
    let ego = bev_box(0.0, 0.0, 0.0, ego[0], ego[1]);
    agents.iter().filter(|a| overlap(a, &ego)).count()
}

/// Speeds (m/s) before the step of a collision driven at speed into a standing agent: one of the two
/// slower than the first (not moving, as [`crate::horizon::MOVING_M_S`] has it), the other faster than
/// the second. Queued vehicles that close up touch at walking pace; a vehicle that did not brake for one
/// standing ahead hits it above the second.
pub const INTO_STANDING_M_S: (f64, f64) = (crate::horizon::MOVING_M_S, 5.0);

/// Collisions that begin between two consecutive frames: pairs of agents (by `track_id`) present in
/// both whose boxes overlap in `next` and did not in `prev`; and of them, those driven at speed into a
/// standing agent ([`INTO_STANDING_M_S`], speeds in `prev`), which a generator that does not brake for
/// what is ahead makes. Each frame's positions are in its own ego frame; overlap does not depend on the
/// frame.
pub fn collision_onsets(prev: &[Agent], next: &[Agent]) -> (usize, usize) {
    let (standing, fast) = INTO_STANDING_M_S;
    let before: std::collections::HashMap<u64, &Agent> = prev.iter().map(|a| (a.track_id, a)).collect();
    let (mut onsets, mut into_standing) = (0, 0);
    for (i, a) in next.iter().enumerate() {
        for b in &next[i + 1..] {
            let (Some(a0), Some(b0)) = (before.get(&a.track_id), before.get(&b.track_id)) else {
                continue;
            };
            if overlap(a, b) && !overlap(a0, b0) {
                onsets += 1;
                let (va, vb) = (a0.vx.hypot(a0.vy), b0.vx.hypot(b0.vy));
                into_standing += usize::from(va.min(vb) < standing && va.max(vb) > fast);
            }
        }
    }
    (onsets, into_standing)
}

/// Mean over frames (with agents) of the fraction of agents that collide; `None` without agents.
pub fn collision_rate<'a>(frames: impl IntoIterator<Item = &'a [Agent]>) -> Option<f64> {
    let rates: Vec<f64> = frames
        .into_iter()
        .filter(|f| !f.is_empty())
        .map(|f| {
            let (h, n) = colliding(f);
            h as f64 / n as f64
        })
        .collect();
    (!rates.is_empty()).then(|| rates.iter().sum::<f64>() / rates.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn car(x: f64, y: f64, heading: f64) -> Agent {
        bev_box(x, y, heading, 4.0, 2.0)
    }

    #[test]
    fn collision_onsets_count_pairs_that_begin_to_overlap() {
        let moving = |id: u64, x: f64, y: f64, vx: f64| Agent {
            track_id: id,
            vx,
            ..car(x, y, 0.0)
        };
        // 1 runs at 10 m/s into 2, which stands; 3 and 4 drive side by side into each other; 5 and 6
        // overlapped already; 7 is new and overlaps 1's new place (no onset: it has no frame before).
        let prev = [
            moving(1, 0.0, 0.0, 10.0),
            moving(2, 6.0, 0.0, 0.0),
            moving(3, 0.0, 10.0, 8.0),
            moving(4, 0.0, 12.5, 8.0),
            moving(5, 0.0, 20.0, 3.0),
            moving(6, 3.0, 20.0, 3.0),
        ];
        let next = [
            moving(1, 5.0, 0.0, 10.0),
            moving(2, 6.0, 0.0, 0.0),
            moving(3, 4.0, 10.0, 8.0),
            moving(4, 4.0, 11.5, 8.0),
            moving(5, 1.5, 20.0, 3.0),
            moving(6, 4.5, 20.0, 3.0),
            moving(7, 5.0, 1.0, 0.0),
        ];
        assert_eq!(collision_onsets(&prev, &next), (2, 1));
        assert_eq!(collision_onsets(&next, &next), (0, 0));
        // Closing up on the standing one at 4 m/s is not at speed.
        let mut creeping = prev;
        creeping[0].vx = 4.0;
        assert_eq!(collision_onsets(&creeping, &next), (2, 0));
    }

    #[test]
    fn rotated_boxes_overlap_exactly_when_they_should() {
        assert!(
            overlap(&car(0.0, 0.0, 0.0), &car(3.0, 0.0, 0.0)),
            "bumpers overlap by 1 m"
        );
        assert!(!overlap(&car(0.0, 0.0, 0.0), &car(4.5, 0.0, 0.0)), "0.5 m gap");
        assert!(!overlap(&car(0.0, 0.0, 0.0), &car(0.0, 2.1, 0.0)), "side by side");
        // Rotated 45° at 3.2 m: its nearest corner reaches 3.2 − √(2² + 1²)·cos(45° − 26.6°) ≈ 1.08 m < 2 m.
        assert!(overlap(
            &car(0.0, 0.0, 0.0),
            &car(3.2, 0.0, std::f64::consts::FRAC_PI_4)
        ));
        // Axis-aligned bounding boxes would overlap here; the rotated boxes do not.
        assert!(!overlap(
            &car(0.0, 0.0, std::f64::consts::FRAC_PI_4),
            &car(2.9, -2.9, std::f64::consts::FRAC_PI_4)
        ));
        let frame = [
            car(0.0, 0.0, 0.0),
            car(3.0, 0.0, 0.0),
            car(20.0, 0.0, 0.0),
            car(40.0, 0.0, 0.0),
        ];
        assert_eq!(colliding(&frame), (2, 4));
        let empty: [Agent; 0] = [];
        assert_eq!(collision_rate([&frame[..], &frame[2..], &empty[..]]), Some(0.25));
    }

    #[test]
    fn agents_on_the_ego_box_are_counted() {
        // The ego 5 × 2 m at the origin along +x; cars 4 × 2 m. Nose to tail: 2.5 + 2 = 4.5 m apart at
        // most; side by side: 1 + 1 = 2 m.
        let up = std::f64::consts::FRAC_PI_2;
        let agents = [
            car(4.4, 0.0, 0.0), // bumpers overlap by 0.1 m
            car(4.6, 0.0, 0.0), // 0.1 m apart
            car(0.0, 1.9, 0.0), // sides overlap
            car(0.0, 2.1, 0.0), // side by side
            car(0.0, 2.9, up),  // across, its end 0.1 m inside the ego's side
            car(0.0, 3.1, up),  // across, 0.1 m clear
        ];
        assert_eq!(overlapping_ego(&agents, [5.0, 2.0]), 3);
        assert_eq!(overlapping_ego(&[], [5.0, 2.0]), 0);
    }
}
