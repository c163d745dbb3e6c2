//! How far kinematics alone predicts a dataset's agents: the position errors of simple predictors
//! against the recorded (unbinned) states, `h` frames ahead. They bound what beating a baseline can mean
//! on a dataset: where the recorded motion is nearly constant-velocity (SUMO's), the constant-velocity
//! baseline is nearly exact and even the recorded acceleration adds little.

use crate::l2::{global_position, global_velocity};
use umgen_scene::{Agent, SceneClip};

/// A predictor of an agent's global position from its last states.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Predictor {
    /// Keeps the last recorded velocity (`umgen eval`'s baseline).
    ConstantVelocity,
    /// Keeps the acceleration between the last two recorded velocities.
    ConstantAcceleration,
    /// Repeats the last frame-to-frame displacement (a velocity from positions only).
    RepeatedDisplacement,
}

impl Predictor {
    /// Every predictor, in report order.
    pub const ALL: [Predictor; 3] = [
        Predictor::ConstantVelocity,
        Predictor::ConstantAcceleration,
        Predictor::RepeatedDisplacement,
    ];

    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Predictor::ConstantVelocity => "constant velocity",
            Predictor::ConstantAcceleration => "constant acceleration",
            Predictor::RepeatedDisplacement => "repeated displacement",
        }
    }

    /// Global position `h` frames of `dt` after `now`, given the agent's previous frame `before` (global
    /// positions and velocities).
    fn predict(self, before: ([f64; 2], [f64; 2]), now: ([f64; 2], [f64; 2]), dt: f64, h: usize) -> [f64; 2] {
        let ((p0, v0), (p, v)) = (before, now);
        let t = dt * h as f64;
        let k = h as f64;
        std::array::from_fn(|i| match self {
            Predictor::ConstantVelocity => p[i] + v[i] * t,
            Predictor::ConstantAcceleration => p[i] + v[i] * t + 0.5 * (v[i] - v0[i]) / dt * t * t,
            Predictor::RepeatedDisplacement => p[i] + (p[i] - p0[i]) * k,
        })
    }
}

/// Errors (m) of every predictor, in [`Predictor::ALL`] order, for each agent of each frame `t` of `clip`
/// that is also recorded at `t − 1` and `t + h` (matched by track id).
pub fn clip_errors(clip: &SceneClip, h: usize) -> [Vec<f64>; 3] {
    let mut out: [Vec<f64>; 3] = Default::default();
    let n = clip.frames.len();
    if h == 0 || n < h + 2 {
        return out;
    }
    let state = |t: usize, id: u64| -> Option<([f64; 2], [f64; 2])> {
        let f = &clip.frames[t];
        let a: &Agent = f.agents.iter().find(|a| a.track_id == id)?;
        Some((global_position(&f.ego, a), global_velocity(&f.ego, a)))
    };
    for t in 1..n - h {
        for a in &clip.frames[t].agents {
            let (Some(before), Some(now), Some((truth, _))) = (
                state(t - 1, a.track_id),
                state(t, a.track_id),
                state(t + h, a.track_id),
            ) else {
                continue;
            };
            for (errors, p) in out.iter_mut().zip(Predictor::ALL) {
                let q = p.predict(before, now, clip.interval, h);
                errors.push((q[0] - truth[0]).hypot(q[1] - truth[1]));
            }
        }
    }
    out
}

/// The value below which a fraction `q` of `values` lie (nearest rank; `None` for no values).
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let i = ((q.clamp(0.0, 1.0) * v.len() as f64).ceil() as usize).clamp(1, v.len().max(1)) - 1;
    v.get(i).copied()
}

#[cfg(test)]
mod tests {
    use super::*;
    use umgen_scene::{AgentCategory, EgoPose, Frame};

    /// A clip of `n` frames of `dt` whose ego stands at the origin facing +y and whose one agent moves
    /// along global +x as `x(t) = x0 + v0 t + a t² / 2`.
    fn clip(n: usize, dt: f64, x0: f64, v0: f64, acc: f64) -> SceneClip {
        let ego = EgoPose {
            x: 0.0,
            y: 0.0,
            heading: std::f64::consts::FRAC_PI_2,
            speed: 0.0,
        };
        let frames = (0..n)
            .map(|i| {
                let t = i as f64 * dt;
                let (x, v) = (x0 + v0 * t + 0.5 * acc * t * t, v0 + acc * t);
                // Global (x, 0) is (0, −x) in the ego's frame (its +x points along global +y).
                let agent = Agent {
                    track_id: 3,
                    category: AgentCategory::Vehicle,
                    x: 0.0,
                    y: -x,
                    z: 0.0,
                    vx: 0.0,
                    vy: -v,
                    vz: 0.0,
                    heading: 0.0,
                    length: 4.0,
                    width: 2.0,
                    height: 1.5,
                };
                Frame {
                    time: t,
                    ego,
                    agents: vec![agent],
                    ..Frame::default()
                }
            })
            .collect();
        SceneClip::new("k", dt, frames).expect("clip")
    }

    #[test]
    fn each_predictor_is_exact_on_its_own_motion_and_off_by_the_known_amount_otherwise() {
        // Steady 8 m/s: every predictor exact, one error per frame that has a past and a future.
        let e = clip_errors(&clip(6, 0.5, 1.0, 8.0, 0.0), 1);
        assert!(
            e.iter().all(|v| v.len() == 4 && v.iter().all(|x| x.abs() < 1e-9)),
            "{e:?}"
        );
        // Braking at 2 m/s²: constant acceleration exact; constant velocity off by a t²/2 = 0.25 m at one
        // step and 1 m at two; the repeated displacement lags by a whole step: a dt² = 0.5 m at one step.
        let c = clip(8, 0.5, 0.0, 10.0, -2.0);
        let [cv, ca, rd] = clip_errors(&c, 1);
        assert!(ca.iter().all(|x| x.abs() < 1e-9), "{ca:?}");
        assert!(cv.iter().all(|x| (x - 0.25).abs() < 1e-9), "{cv:?}");
        assert!(rd.iter().all(|x| (x - 0.5).abs() < 1e-9), "{rd:?}");
        let [cv2, ca2, _] = clip_errors(&c, 2);
        assert_eq!(cv2.len(), 5);
        assert!(cv2.iter().all(|x| (x - 1.0).abs() < 1e-9) && ca2.iter().all(|x| x.abs() < 1e-9));
        // Too short a clip for the horizon, or no horizon: nothing.
        assert!(
            clip_errors(&clip(3, 0.5, 0.0, 1.0, 0.0), 2)
                .iter()
                .all(Vec::is_empty)
        );
        assert!(clip_errors(&c, 0).iter().all(Vec::is_empty));
    }

    #[test]
    fn quantiles_by_nearest_rank() {
        let v = [5.0, 1.0, 4.0, 2.0, 3.0];
        assert_eq!(quantile(&v, 0.5), Some(3.0));
        assert_eq!(quantile(&v, 0.9), Some(5.0));
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&[], 0.5), None);
    }
}
