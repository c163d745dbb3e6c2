//! The horizon statistics on hand-placed frames.

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
    s.add(&f1, &[], 0.5, Some(&road));
    s.add(&f2, std::slice::from_ref(&f1), 0.5, Some(&road));
    let r = s.summary();
    assert_eq!(r.frames, 2);
    assert_eq!(r.agents_mean, Some(2.5));
    assert_eq!(r.agents_distribution, vec![0.0, 0.0, 0.5, 0.5]);
    assert_eq!(
        (r.entries_per_s, r.exits_per_s),
        (Some(4.0), Some(2.0)),
        "2 in and 1 out in 0.5 s"
    );
    // The rates' counts, and their intervals from the counts (not from the rates).
    let c = &r.counts;
    assert_eq!((c.entries, c.exits, c.onsets, c.seconds), (2, 1, 0, 0.5));
    assert_eq!(c.entries_per_s_95, rate_95(2, 0.5));
    let [lo, hi] = c.exits_per_s_95.unwrap_or_default();
    assert!(
        lo < 2.0 && 2.0 < hi && lo > 0.0,
        "one exit in 0.5 s: [{lo}, {hi}] around 2/s"
    );
    assert_eq!(c.onsets_per_s_95.map(|[lo, _]| lo), Some(0.0));
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
    // None left the road: agent 2 was off it in both frames, 3 and 4 entered off it.
    let leaving = r.counts.leaving_road.as_ref().map(|l| (l.vehicles, l.moving));
    assert_eq!(leaving, Some((0, 0)));
    // Both egos stand at the origin, on the road; one moved to y = 50 is off it.
    assert_eq!(r.ego_off_road_rate, Some(0.0));
    assert_eq!(r.vehicle_off_road_ego_on_rate, r.vehicle_off_road_rate);
    let mut off = f1.clone();
    off.ego.y = 50.0;
    s.add(&off, &[], 0.5, Some(&road));
    let with_off = s.summary();
    assert_eq!(with_off.ego_off_road_rate, Some(1.0 / 3.0));
    // Agent 1 rides with that ego to global (10, 50), off the road; the frames whose ego is on it keep
    // their vehicles' rate.
    assert_eq!(with_off.vehicle_off_road_rate, Some(3.0 / 5.0));
    assert_eq!(with_off.vehicle_off_road_ego_on_rate, Some(2.0 / 4.0));
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
    s.add(&f1, &[], 0.5, Some(&road));
    s.add(&f2, std::slice::from_ref(&f1), 0.5, Some(&road));
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
    blind.add(&f1, &[], 0.5, None);
    blind.add(&f2, std::slice::from_ref(&f1), 0.5, None);
    assert_eq!(blind.summary().entering_off_road_rate, None);
    assert_eq!(blind.summary().counts.leaving_road, None, "no map");
    assert_eq!(blind.summary().ego_overlap_rate, None, "no ego box given");
    // Vehicle 1 stands on the ego (at the origin) in frame 1 and 7 m aside in frame 2.
    let mut ego = SceneStats::with_ego_box([5.0, 2.0]);
    ego.add(&f1, &[], 0.5, None);
    ego.add(&f2, std::slice::from_ref(&f1), 0.5, None);
    assert_eq!(ego.summary().ego_overlap_rate, Some(0.5));
}

#[test]
fn standing_agents_that_drive_off_and_approaches() {
    // Agents 1 and 2 stand; 3 drives at 10 m/s along +x towards 2, 16 m ahead of it bumper to bumper.
    // Half a second later 1 drives off at 3 m/s, 2 still stands, 3 braked to 9 m/s (2 m/s²).
    let f1 = frame(
        0.0,
        vec![
            agent(1, 0.0, 30.0, 0.0, 0.0, 0.0),
            agent(2, 20.0, 0.0, 0.0, 0.0, 0.0),
            agent(3, 0.0, 0.0, 10.0, 0.0, 0.0),
        ],
    );
    let f2 = frame(
        0.0,
        vec![
            agent(1, 1.5, 30.0, 3.0, 0.0, 0.0),
            agent(2, 20.0, 0.0, 0.0, 0.0, 0.0),
            agent(3, 4.75, 0.0, 9.0, 0.0, 0.0),
        ],
    );
    let mut s = SceneStats::default();
    s.add(&f1, &[], 0.5, None);
    s.add(&f2, std::slice::from_ref(&f1), 0.5, None);
    let r = s.summary();
    // One of two standing agents drove off in one 0.5 s step.
    assert_eq!(r.starts_per_standing_s, Some(0.5 / 0.5));
    assert_eq!((r.approaches_per_s, r.approach_braking), (Some(2.0), Some(1.0)));
    // Frame 2 again after itself: 2 stands once more and stays, 1 moved already: 1 start of 3.
    s.add(&f2, &[f1.clone(), f2.clone()], 0.5, None);
    let r = s.summary();
    assert_eq!(r.starts_per_standing_s, Some(1.0 / 3.0 / 0.5));
    // 2 still stands and 3 still approaches at 9 m/s without slowing down: 2 approaches in 1 s.
    assert_eq!((r.approaches_per_s, r.approach_braking), (Some(2.0), Some(0.5)));
    // 3 had braked from 10 to 9 m/s over the step before, so neither approach began unbraked.
    assert_eq!(r.approach_braking_onset, None);
    // Once more: now 3 kept 9 m/s over the step before and keeps it again, an unbraked approach
    // without braking.
    s.add(&f2, &[f1.clone(), f2.clone(), f2.clone()], 0.5, None);
    assert_eq!(s.summary().approach_braking_onset, Some(0.0));
}

#[test]
fn seconds_of_the_horizon() {
    let s: Vec<usize> = (1..=5).map(|h| second_of(h, 0.5)).collect();
    assert_eq!(s, [1, 1, 2, 2, 3]);
    assert_eq!(second_of(1, 0.1), 1);
    assert_eq!(second_of(10, 0.1), 1);
    assert_eq!(second_of(11, 0.1), 2);
}

#[test]
fn entries_and_exits_inside_the_range_or_across_its_edge() {
    let at = |x: f64, heading: f64, agents| Frame {
        ego: EgoPose {
            x,
            y: 0.0,
            heading,
            speed: 0.0,
        },
        agents,
        ..Frame::default()
    };
    // Ranges ±10 m. Frame 1, ego at the origin: agent 1 at x = 9 driving out at 4 m/s; agent 2 standing
    // at the centre; agent 5 standing behind at x = -8; agent 7 stays.
    let f1 = at(
        0.0,
        0.0,
        vec![
            agent(1, 9.0, 0.0, 4.0, 0.0, 0.0),
            agent(2, 0.0, 0.0, 0.0, 0.0, 0.0),
            agent(5, -8.0, 0.0, 0.0, 0.0, 0.0),
            agent(7, 0.0, 6.0, 0.0, 0.0, 0.0),
        ],
    );
    // Frame 2, 0.5 s later, the ego 5 m further along x (its range now global x from -5 to 15). Agent 3
    // enters at the front edge driving towards the ego at 4 m/s: a step before it was at global 16.5,
    // beyond the old range. Agent 4 appears standing at (2, 2), global (7, 2): inside the old range.
    let f2 = at(
        5.0,
        0.0,
        vec![
            agent(7, -5.0, 6.0, 0.0, 0.0, 0.0),
            agent(3, 9.5, -4.0, -4.0, 0.0, 0.0),
            agent(4, 2.0, 2.0, 0.0, 0.0, 0.0),
        ],
    );
    let mut s = SceneStats::default().within([-10.0, 10.0], [-10.0, 10.0]);
    s.add(&f1, &[], 0.5, None);
    s.add(&f2, std::slice::from_ref(&f1), 0.5, None);
    let c = s.summary().counts;
    assert_eq!((c.entries, c.exits), (2, 3));
    // Entries: 3 across the edge, 4 inside. Exits: agent 1 would be at global 11, local 6 in the new
    // frame (the ego followed it), and agent 2 at local -5: both vanished inside; agent 5, standing at
    // global -8, is local -13: left across the edge, though it did not move.
    assert_eq!((c.entries_inside, c.exits_inside), (Some(1), Some(2)));
    // Without a range nothing is told apart.
    let mut plain = SceneStats::default();
    plain.add(&f1, &[], 0.5, None);
    plain.add(&f2, std::slice::from_ref(&f1), 0.5, None);
    let p = plain.summary().counts;
    assert_eq!((p.entries_inside, p.exits_inside), (None, None));
}
