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
}
