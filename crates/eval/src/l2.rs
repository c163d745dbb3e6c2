//! L2 position errors against ground truth over a horizon, for a model's rollout and for the
//! constant-velocity baseline (ego and agents keep their last velocity). Agents are matched by
//! `track_id` (for decoded scenes: the slot) and compared in global coordinates, through each scene's own
//! ego pose.

use umgen_scene::{Agent, EgoAction, EgoPose};

/// An agent's global position.
pub fn global_position(ego: &EgoPose, a: &Agent) -> [f64; 2] {
    ego.pose2().to_parent([a.x, a.y])
}

/// An agent's global velocity.
pub fn global_velocity(ego: &EgoPose, a: &Agent) -> [f64; 2] {
    ego.pose2().rotate_to_parent([a.vx, a.vy])
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// Ego position error per horizon step (`[0]` = one step ahead).
pub fn ego_l2(predicted: &[EgoPose], truth: &[EgoPose]) -> Vec<f64> {
    predicted
        .iter()
        .zip(truth)
        .map(|(p, t)| dist([p.x, p.y], [t.x, t.y]))
        .collect()
}

/// The ego keeps repeating its last motion: `steps` poses after `last`.
pub fn constant_velocity_ego(last: &EgoPose, action: &EgoAction, dt: f64, steps: usize) -> Vec<EgoPose> {
    let mut out = Vec::with_capacity(steps);
    let mut p = *last;
    for _ in 0..steps {
        p = p.advance(action, dt);
        out.push(p);
    }
    out
}

/// Global positions of agents by track id after `h` steps of `dt` at their last velocity.
pub fn constant_velocity_agents(ego: &EgoPose, agents: &[Agent], dt: f64, h: usize) -> Vec<(u64, [f64; 2])> {
    agents
        .iter()
        .map(|a| {
            let p = global_position(ego, a);
            let v = global_velocity(ego, a);
            let t = dt * h as f64;
            (a.track_id, [p[0] + v[0] * t, p[1] + v[1] * t])
        })
        .collect()
}

/// Global positions of agents by track id after `h` steps of `dt` at constant acceleration: each agent's
/// global velocity change since the frame before (`before_ego`, `before`, matched by track id) per `dt`,
/// kept; an agent not in the frame before keeps its velocity. The kinematic prediction `backbone.track`
/// hints the model with when `track_accel` is on (there in each frame's coordinates, one frame ahead).
pub fn constant_acceleration_agents(
    before_ego: &EgoPose,
    before: &[Agent],
    ego: &EgoPose,
    agents: &[Agent],
    dt: f64,
    h: usize,
) -> Vec<(u64, [f64; 2])> {
    let t = dt * h as f64;
    agents
        .iter()
        .map(|a| {
            let p = global_position(ego, a);
            let v = global_velocity(ego, a);
            let v0 = before
                .iter()
                .find(|b| b.track_id == a.track_id)
                .map_or(v, |b| global_velocity(before_ego, b));
            let at = |i: usize| p[i] + v[i] * t + 0.5 * (v[i] - v0[i]) / dt * t * t;
            (a.track_id, [at(0), at(1)])
        })
        .collect()
}

/// Global predictions moved onto a token model's grid: each position is taken into the frame of `ego` (the
/// pose whose frame the tokens are in), rounded by `round` (to the centre of its bin per coordinate) and
/// taken back. A token model can only name bin centres, so this is the baseline it would score if it
/// implemented constant velocity exactly; the difference from the continuous baseline is the price of the
/// bins alone.
pub fn on_grid(
    ego: &EgoPose,
    predicted: &[(u64, [f64; 2])],
    mut round: impl FnMut([f64; 2]) -> [f64; 2],
) -> Vec<(u64, [f64; 2])> {
    let frame = ego.pose2();
    predicted
        .iter()
        .map(|(id, p)| (*id, frame.to_parent(round(frame.to_local(*p)))))
        .collect()
}

/// Distances between predicted and true global positions of the agents present in both (matched by track
/// id), in the order of `predicted`.
pub fn agent_errors(predicted: &[(u64, [f64; 2])], truth: &[(u64, [f64; 2])]) -> Vec<f64> {
    predicted
        .iter()
        .filter_map(|(id, p)| truth.iter().find(|(t, _)| t == id).map(|(_, q)| dist(*p, *q)))
        .collect()
}

/// Mean distance between predicted and true global positions of the agents present in both (matched by
/// track id), and how many were matched; `None` when none match.
pub fn agent_l2(predicted: &[(u64, [f64; 2])], truth: &[(u64, [f64; 2])]) -> Option<(f64, usize)> {
    let d = agent_errors(predicted, truth);
    (!d.is_empty()).then(|| (d.iter().sum::<f64>() / d.len() as f64, d.len()))
}

/// The median of `values` (the mean of the two middle ones for an even count); `None` when empty. A
/// mean of agent errors is ruled by the few agents a model loses; the median says how close a typical
/// one stays.
pub fn median(values: &[f64]) -> Option<f64> {
    quantile(values, 0.5)
}

/// The `q` quantile of `values` (`0 ≤ q ≤ 1`), interpolated linearly between the two nearest of the
/// sorted values (as NumPy's default); `None` when empty or `q` is outside `[0, 1]`.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    if values.is_empty() || !(0.0..=1.0).contains(&q) {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let at = q * (v.len() - 1) as f64;
    let (lo, hi) = (at.floor() as usize, at.ceil() as usize);
    Some(v[lo] + (at - lo as f64) * (v[hi] - v[lo]))
}

/// Global positions by track id of a frame's agents.
pub fn positions(ego: &EgoPose, agents: &[Agent]) -> Vec<(u64, [f64; 2])> {
    agents
        .iter()
        .map(|a| (a.track_id, global_position(ego, a)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use umgen_scene::AgentCategory;

    fn agent(id: u64, x: f64, y: f64, vx: f64, vy: f64) -> Agent {
        Agent {
            track_id: id,
            category: AgentCategory::Vehicle,
            x,
            y,
            z: 0.0,
            vx,
            vy,
            vz: 0.0,
            heading: 0.0,
            length: 4.0,
            width: 2.0,
            height: 1.5,
        }
    }

    #[test]
    fn known_offsets_give_known_errors_and_steady_motion_fools_no_baseline() {
        let pose = |x: f64, y: f64| EgoPose {
            x,
            y,
            heading: 0.0,
            speed: 0.0,
        };
        assert_eq!(
            ego_l2(
                &[pose(3.0, 4.0), pose(1.0, 1.0)],
                &[pose(0.0, 0.0), pose(1.0, 1.0)]
            ),
            vec![5.0, 0.0]
        );
        // An ego driving straight at 2 m per step: the baseline is exact.
        let cv = constant_velocity_ego(&pose(0.0, 0.0), &EgoAction::new(2.0, 0.0, 0.0), 0.5, 3);
        assert_eq!(
            ego_l2(&cv, &[pose(2.0, 0.0), pose(4.0, 0.0), pose(6.0, 0.0)]),
            vec![0.0, 0.0, 0.0]
        );
        // An ego facing +y (heading π/2) sees an agent 10 m ahead at (0, 10) globally, moving at its
        // local (1, 0) m/s, i.e. globally (0, 1).
        let ego = EgoPose {
            x: 0.0,
            y: 0.0,
            heading: std::f64::consts::FRAC_PI_2,
            speed: 0.0,
        };
        let a = agent(7, 10.0, 0.0, 1.0, 0.0);
        let p = global_position(&ego, &a);
        assert!(p[0].abs() < 1e-9 && (p[1] - 10.0).abs() < 1e-9);
        let cv = constant_velocity_agents(&ego, &[a], 0.5, 4);
        assert!((cv[0].1[1] - 12.0).abs() < 1e-9, "{:?}", cv[0]);
        // Matching by id; a 3-4-5 offset; unmatched agents ignored.
        let got = agent_l2(
            &[(7, [3.0, 4.0]), (8, [0.0, 0.0])],
            &[(7, [0.0, 0.0]), (9, [1.0, 1.0])],
        );
        assert_eq!(got, Some((5.0, 1)));
        assert_eq!(agent_l2(&[(1, [0.0, 0.0])], &[(2, [0.0, 0.0])]), None);
        let each = agent_errors(
            &[(7, [3.0, 4.0]), (8, [0.0, 0.0]), (9, [1.0, 2.0])],
            &[(9, [1.0, 1.0]), (7, [0.0, 0.0])],
        );
        assert_eq!(each, vec![5.0, 1.0]);
    }

    #[test]
    fn constant_acceleration_keeps_the_velocity_change_of_the_last_frame() {
        // Ego at the origin facing +y, then at (0, 2) still facing +y. Agent 3: local velocity (2, 0)
        // before, (3, 0) now (globally (0, 2) → (0, 3)), at local (10, 0), i.e. global (0, 12): with
        // dt 0.5 its acceleration is 2 m/s², so after 2 steps (1 s) it is at 12 + 3 · 1 + ½ · 2 · 1² = 16.
        // Agent 5 is new in the frame: constant velocity, (1, 0) local = (0, 1) global, from (0, 2 + 4).
        let facing_y = |y: f64| EgoPose {
            x: 0.0,
            y,
            heading: std::f64::consts::FRAC_PI_2,
            speed: 0.0,
        };
        let (before_ego, ego) = (facing_y(0.0), facing_y(2.0));
        let before = [agent(3, 11.0, 0.0, 2.0, 0.0)];
        let now = [agent(3, 10.0, 0.0, 3.0, 0.0), agent(5, 4.0, 0.0, 1.0, 0.0)];
        let got = constant_acceleration_agents(&before_ego, &before, &ego, &now, 0.5, 2);
        let want = [(3, [0.0, 16.0]), (5, [0.0, 7.0])];
        for ((id, p), (wid, w)) in got.iter().zip(want) {
            assert_eq!(*id, wid);
            assert!(
                (p[0] - w[0]).abs() < 1e-9 && (p[1] - w[1]).abs() < 1e-9,
                "{id}: {p:?} vs {w:?}"
            );
        }
        // Without a velocity change it is constant velocity.
        let steady = constant_acceleration_agents(&ego, &now, &ego, &now, 0.5, 3);
        assert_eq!(steady, constant_velocity_agents(&ego, &now, 0.5, 3));
    }

    #[test]
    fn predictions_on_the_grid_of_the_ego_frame() {
        // Ego at (10, 0) facing +y: global (9.7, 3.3) is local (3.3, 0.3), (9.7, -0.2) is local (-0.2, 0.3)
        // (no point on a bin edge, where the rotation's rounding would pick the side).
        let ego = EgoPose {
            x: 10.0,
            y: 0.0,
            heading: std::f64::consts::FRAC_PI_2,
            speed: 0.0,
        };
        // One-metre bins with centres at k + 0.5.
        let round = |p: [f64; 2]| p.map(|v| v.floor() + 0.5);
        let got = on_grid(&ego, &[(4, [9.7, 3.3]), (9, [9.7, -0.2])], round);
        // Local (3.5, 0.5) → global (9.5, 3.5); local (-0.5, 0.5) → global (9.5, -0.5).
        let want = [(4, [9.5, 3.5]), (9, [9.5, -0.5])];
        for ((id, p), (wid, w)) in got.iter().zip(want) {
            assert_eq!(*id, wid);
            assert!(
                (p[0] - w[0]).abs() < 1e-9 && (p[1] - w[1]).abs() < 1e-9,
                "{p:?} vs {w:?}"
            );
        }
    }

    #[test]
    fn medians_of_odd_even_and_empty_sets() {
        // One lost agent moves the mean (22.6) and not the median.
        assert_eq!(median(&[0.2, 110.0, 0.1, 0.3, 2.0]), Some(0.3));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&[]), None);
    }

    #[test]
    fn quantiles_interpolate_between_sorted_values() {
        let v = [5.0, 1.0, 4.0, 2.0, 3.0];
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&v, 1.0), Some(5.0));
        // 0.9 · 4 = 3.6: between the 4th (4.0) and 5th (5.0) values.
        assert!((quantile(&v, 0.9).unwrap() - 4.6).abs() < 1e-12);
        assert_eq!(quantile(&[7.0], 0.9), Some(7.0));
        assert_eq!(quantile(&v, 1.5), None);
        assert_eq!(quantile(&v, f64::NAN), None);
        assert_eq!(quantile(&[], 0.5), None);
    }
}
