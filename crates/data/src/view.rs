//! Ego-centred frames from log states: the ego's pose and action, and the agents around it in its frame.

use crate::error::{Result, corrupt};
use crate::log::{State, Track};
use std::path::Path;
use umgen_scene::{Agent, EgoAction, EgoPose, Frame, Pose2, wrap_angle};

/// How frames are cut from logs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewOptions {
    /// Agents whose centre lies within ±`agent_range` metres of the ego along both ego axes are kept
    /// (the paper's 128 m × 128 m window by default).
    pub agent_range: f64,
}

impl Default for ViewOptions {
    fn default() -> Self {
        Self { agent_range: 64.0 }
    }
}

/// The ego pose of a state.
pub fn ego_pose(s: &State) -> EgoPose {
    EgoPose {
        x: f64::from(s.x),
        y: f64::from(s.y),
        heading: wrap_angle(f64::from(s.heading)),
        speed: f64::from(s.speed),
    }
}

/// The agent a state shows in the frame of `ego`.
pub fn agent_in_frame(track: &Track, index: u32, s: &State, ego: &Pose2) -> Agent {
    let [x, y] = ego.to_local([f64::from(s.x), f64::from(s.y)]);
    let h = f64::from(s.heading);
    let speed = f64::from(s.speed);
    let [vx, vy] = ego.rotate_to_local([speed * h.cos(), speed * h.sin()]);
    Agent {
        track_id: u64::from(index),
        category: track.category,
        x,
        y,
        // Boxes stand on flat ground; the ego frame's origin is on the ground.
        z: track.height / 2.0,
        vx,
        vy,
        vz: 0.0,
        heading: wrap_angle(h - ego.heading),
        length: track.length,
        width: track.width,
        height: track.height,
    }
}

/// Frames of one ego over a sequence of steps.
///
/// `steps` are the states of each sampled step, `before` the ego's state one sampling gap before the
/// first (if the log has it), `frame_dt` the seconds between sampled steps. The first frame's action is
/// the true motion from `before` when known, else the distance its speed covers in `frame_dt`.
pub fn frames(
    path: &Path,
    tracks: &[Track],
    ego: u32,
    steps: &[&[State]],
    before: Option<&State>,
    frame_dt: f64,
    options: &ViewOptions,
) -> Result<Vec<Frame>> {
    let mut out: Vec<Frame> = Vec::with_capacity(steps.len());
    let mut prev = before.map(|s| ego_pose(s).pose2());
    for (i, states) in steps.iter().enumerate() {
        let own = states
            .binary_search_by_key(&ego, |s| s.track)
            .map(|k| &states[k])
            .map_err(|_| corrupt(path, format!("ego track {ego} is absent from sampled step {i}")))?;
        let pose = ego_pose(own);
        let p2 = pose.pose2();
        let action = match prev {
            Some(p) => EgoAction::between(&p, &p2),
            None => EgoAction::new(pose.speed * frame_dt, 0.0, 0.0),
        };
        let r = options.agent_range;
        let agents = states
            .iter()
            .filter(|s| s.track != ego)
            .filter_map(|s| {
                let track = tracks.get(s.track as usize)?;
                let a = agent_in_frame(track, s.track, s, &p2);
                (a.x.abs() <= r && a.y.abs() <= r).then_some(a)
            })
            .collect();
        out.push(Frame {
            time: i as f64 * frame_dt,
            ego: pose,
            action,
            agents,
            ..Frame::default()
        });
        prev = Some(p2);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;
    use umgen_scene::AgentCategory;

    fn track(category: AgentCategory) -> Track {
        Track {
            name: "t".into(),
            category,
            class: "passenger".into(),
            length: 4.0,
            width: 2.0,
            height: 1.6,
        }
    }

    #[test]
    fn an_agent_10_m_ahead_is_at_x_10() {
        // Ego at (100, 50) facing +y (north); the other car 10 m further north, same heading, 5 m/s.
        let tracks = vec![track(AgentCategory::Vehicle), track(AgentCategory::Vehicle)];
        let h = FRAC_PI_2 as f32;
        let step = [
            State {
                track: 0,
                x: 100.0,
                y: 50.0,
                heading: h,
                speed: 8.0,
            },
            State {
                track: 1,
                x: 100.0,
                y: 60.0,
                heading: h,
                speed: 5.0,
            },
        ];
        let before = State {
            track: 0,
            x: 100.0,
            y: 46.0,
            heading: h,
            speed: 8.0,
        };
        let f = frames(
            Path::new("x"),
            &tracks,
            0,
            &[&step],
            Some(&before),
            0.5,
            &ViewOptions::default(),
        )
        .unwrap();
        let a = &f[0].agents[0];
        assert!((a.x - 10.0).abs() < 1e-5 && a.y.abs() < 1e-5, "{a:?}");
        assert!((a.vx - 5.0).abs() < 1e-5 && a.vy.abs() < 1e-5 && a.heading.abs() < 1e-6);
        assert!((a.z - 0.8).abs() < 1e-12);
        assert!((f[0].action.dx - 4.0).abs() < 1e-5 && f[0].action.dy.abs() < 1e-5);
        // Without a previous state the action comes from the speed.
        let f = frames(
            Path::new("x"),
            &tracks,
            0,
            &[&step],
            None,
            0.5,
            &ViewOptions::default(),
        )
        .unwrap();
        assert!((f[0].action.dx - 4.0).abs() < 1e-9);
    }

    #[test]
    fn agents_outside_the_window_are_dropped_and_a_missing_ego_is_an_error() {
        let tracks = vec![track(AgentCategory::Vehicle), track(AgentCategory::Pedestrian)];
        let step = [
            State {
                track: 0,
                x: 0.0,
                y: 0.0,
                heading: 0.0,
                speed: 0.0,
            },
            State {
                track: 1,
                x: 0.0,
                y: 70.0,
                heading: 0.0,
                speed: 1.0,
            },
        ];
        let f = frames(
            Path::new("x"),
            &tracks,
            0,
            &[&step],
            None,
            0.5,
            &ViewOptions::default(),
        )
        .unwrap();
        assert!(f[0].agents.is_empty());
        let wide = ViewOptions { agent_range: 80.0 };
        assert_eq!(
            frames(Path::new("x"), &tracks, 0, &[&step], None, 0.5, &wide).unwrap()[0]
                .agents
                .len(),
            1
        );
        let err = frames(Path::new("log.ulog"), &tracks, 5, &[&step], None, 0.5, &wide)
            .unwrap_err()
            .to_string();
        assert!(err.contains("log.ulog") && err.contains("ego track 5"), "{err}");
    }
}
