//! How far kinematics alone predicts a dataset's agents: the position errors of simple predictors
//! against the recorded (unbinned) states, `h` frames ahead. They bound what beating a baseline can mean
//! on a dataset: where the recorded motion is nearly constant-velocity (SUMO's), the constant-velocity
//! baseline is nearly exact and even the recorded acceleration adds little.

use crate::l2::{global_position, global_velocity};
use umgen_scene::{Agent, AgentCategory, SceneClip};

/// A predictor of an agent's global position from its last states.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Predictor {
    /// Keeps the last recorded velocity (`umgen eval`'s baseline).
    ConstantVelocity,
    /// Keeps the acceleration between the last two recorded velocities.
    ConstantAcceleration,
    /// Repeats the last frame-to-frame displacement (a velocity from positions only).
    RepeatedDisplacement,
    /// Keeps the velocity's turn rate and its speed's change between the last two recorded velocities
    /// (constant turn rate and acceleration): follows a bend where constant acceleration runs straight.
    ConstantTurn,
}

/// Below this speed (m/s) in either recorded frame a velocity's direction says little about a turn, and
/// [`Predictor::ConstantTurn`] keeps the acceleration instead.
const TURN_MIN_SPEED: f64 = 0.5;

/// Integration steps a frame of [`Predictor::ConstantTurn`]'s motion is divided into (midpoint rule: an
/// error well under a millimetre for a frame of 0.5 s at urban speeds and turn rates).
const TURN_SUBSTEPS: usize = 64;

impl Predictor {
    /// Every predictor, in report order.
    pub const ALL: [Predictor; 4] = [
        Predictor::ConstantVelocity,
        Predictor::ConstantAcceleration,
        Predictor::RepeatedDisplacement,
        Predictor::ConstantTurn,
    ];

    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Predictor::ConstantVelocity => "constant velocity",
            Predictor::ConstantAcceleration => "constant acceleration",
            Predictor::RepeatedDisplacement => "repeated displacement",
            Predictor::ConstantTurn => "constant turn rate",
        }
    }

    /// Global position `h` frames of `dt` after `now`, given the agent's previous frame `before` (global
    /// positions and velocities).
    fn predict(self, before: ([f64; 2], [f64; 2]), now: ([f64; 2], [f64; 2]), dt: f64, h: usize) -> [f64; 2] {
        let ((p0, v0), (p, v)) = (before, now);
        let t = dt * h as f64;
        let k = h as f64;
        if self == Predictor::ConstantTurn
            && let Some(q) = turning(p, v0, v, dt, t)
        {
            return q;
        }
        std::array::from_fn(|i| match self {
            Predictor::ConstantVelocity => p[i] + v[i] * t,
            Predictor::ConstantAcceleration | Predictor::ConstantTurn => {
                p[i] + v[i] * t + 0.5 * (v[i] - v0[i]) / dt * t * t
            }
            Predictor::RepeatedDisplacement => p[i] + (p[i] - p0[i]) * k,
        })
    }
}

/// Position `t` seconds after `p` for a velocity `v` whose direction turns and whose speed changes at the
/// rates they did over the `dt` since the previous velocity `v0`; the speed stops at zero rather than
/// turning the agent around. `None` where either speed is under [`TURN_MIN_SPEED`].
fn turning(p: [f64; 2], v0: [f64; 2], v: [f64; 2], dt: f64, t: f64) -> Option<[f64; 2]> {
    let (s0, s) = (v0[0].hypot(v0[1]), v[0].hypot(v[1]));
    if s0.min(s) < TURN_MIN_SPEED {
        return None;
    }
    let heading = v[1].atan2(v[0]);
    // The turn since the previous frame, wrapped to (−π, π].
    let turn = (heading - v0[1].atan2(v0[0]) + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
        - std::f64::consts::PI;
    let (omega, acc) = (turn / dt, (s - s0) / dt);
    let steps = TURN_SUBSTEPS * (t / dt).ceil().max(1.0) as usize;
    let h = t / steps as f64;
    let mut q = p;
    for i in 0..steps {
        let tm = (i as f64 + 0.5) * h;
        let speed = (s + acc * tm).max(0.0);
        let angle = heading + omega * tm;
        q[0] += speed * angle.cos() * h;
        q[1] += speed * angle.sin() * h;
    }
    Some(q)
}

/// Errors (m) of every predictor, in [`Predictor::ALL`] order, for each agent of each frame `t` of `clip`
/// that is also recorded at `t − 1` and `t + h` (matched by track id), of `category` only where given.
pub fn clip_errors(
    clip: &SceneClip,
    h: usize,
    category: Option<AgentCategory>,
) -> [Vec<f64>; Predictor::ALL.len()] {
    let mut out: [Vec<f64>; Predictor::ALL.len()] = Default::default();
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
            if category.is_some_and(|c| c != a.category) {
                continue;
            }
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

    /// A clip of `n` frames of `dt` whose ego stands at the origin facing global +y and whose one agent
    /// is at the global position and velocity `motion(t)`.
    fn clip_along(n: usize, dt: f64, motion: impl Fn(f64) -> ([f64; 2], [f64; 2])) -> SceneClip {
        let ego = EgoPose {
            x: 0.0,
            y: 0.0,
            heading: std::f64::consts::FRAC_PI_2,
            speed: 0.0,
        };
        let frames = (0..n)
            .map(|i| {
                let t = i as f64 * dt;
                let ([x, y], [vx, vy]) = motion(t);
                // Global (x, y) is (y, −x) in the ego's frame (its +x points along global +y).
                let agent = Agent {
                    track_id: 3,
                    category: AgentCategory::Vehicle,
                    x: y,
                    y: -x,
                    z: 0.0,
                    vx: vy,
                    vy: -vx,
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

    /// An agent moving along global +x as `x(t) = x0 + v0 t + a t² / 2`.
    fn clip(n: usize, dt: f64, x0: f64, v0: f64, acc: f64) -> SceneClip {
        clip_along(n, dt, |t| {
            ([x0 + v0 * t + 0.5 * acc * t * t, 0.0], [v0 + acc * t, 0.0])
        })
    }

    #[test]
    fn each_predictor_is_exact_on_its_own_motion_and_off_by_the_known_amount_otherwise() {
        // Steady 8 m/s: every predictor exact, one error per frame that has a past and a future.
        let e = clip_errors(&clip(6, 0.5, 1.0, 8.0, 0.0), 1, None);
        assert!(
            e.iter().all(|v| v.len() == 4 && v.iter().all(|x| x.abs() < 1e-9)),
            "{e:?}"
        );
        // Braking at 2 m/s²: constant acceleration exact; constant velocity off by a t²/2 = 0.25 m at one
        // step and 1 m at two; the repeated displacement lags by a whole step: a dt² = 0.5 m at one step.
        let c = clip(8, 0.5, 0.0, 10.0, -2.0);
        let [cv, ca, rd, ct] = clip_errors(&c, 1, None);
        assert!(ca.iter().all(|x| x.abs() < 1e-9), "{ca:?}");
        assert!(ct.iter().all(|x| x.abs() < 1e-9), "{ct:?}");
        assert!(cv.iter().all(|x| (x - 0.25).abs() < 1e-9), "{cv:?}");
        assert!(rd.iter().all(|x| (x - 0.5).abs() < 1e-9), "{rd:?}");
        let [cv2, ca2, _, _] = clip_errors(&c, 2, None);
        assert_eq!(cv2.len(), 5);
        assert!(cv2.iter().all(|x| (x - 1.0).abs() < 1e-9) && ca2.iter().all(|x| x.abs() < 1e-9));
        // Too short a clip for the horizon, or no horizon: nothing.
        assert!(
            clip_errors(&clip(3, 0.5, 0.0, 1.0, 0.0), 2, None)
                .iter()
                .all(Vec::is_empty)
        );
        assert!(clip_errors(&c, 0, None).iter().all(Vec::is_empty));
        // The clip's one agent is a vehicle: counted as one, not as a pedestrian.
        let vehicles = clip_errors(&c, 1, Some(AgentCategory::Vehicle));
        assert_eq!(vehicles[1].len(), ca.len());
        assert!(
            clip_errors(&c, 1, Some(AgentCategory::Pedestrian))
                .iter()
                .all(Vec::is_empty)
        );
    }

    #[test]
    fn the_turning_predictor_follows_a_circle_and_stops_where_braking_ends() {
        // 8 m/s around a circle of 20 m radius (0.4 rad/s): a quarter turn in 4 s.
        let (r, w) = (20.0, 0.4);
        let c = clip_along(12, 0.5, |t| {
            let a = w * t;
            (
                [r * a.sin(), r * (1.0 - a.cos())],
                [r * w * a.cos(), r * w * a.sin()],
            )
        });
        for h in [1, 4, 8] {
            let [_, ca, _, ct] = clip_errors(&c, h, None);
            assert!(ct.iter().all(|x| *x < 1e-4), "{h} ahead: {ct:?}");
            // Constant acceleration runs along the parabola: at 8 frames (4 s, a quarter turn) metres off.
            let k = (0.5 * h as f64).powi(2);
            assert!(ca.iter().all(|x| *x > 0.01 * k), "{h} ahead: {ca:?}");
        }
        // Under 0.5 m/s a velocity's direction is noise: the same circle at 0.4 m/s is predicted by the
        // acceleration alone.
        let slow = clip_along(6, 0.5, |t| {
            let a = 0.4 * t;
            ([a.sin(), 1.0 - a.cos()], [0.4 * a.cos(), 0.4 * a.sin()])
        });
        let [_, ca, _, ct] = clip_errors(&slow, 2, None);
        assert_eq!(ca, ct);
        // Braking at 2 m/s² from 3 m/s stops after 1.5 s, 2.25 m on. From t = 0.5 s (2.5 m/s, 1.25 m gone)
        // three frames ahead (t = 2 s, half a second after the stop), constant acceleration has driven back
        // to 2.0 m; the turning predictor stays where the agent stopped.
        let c = clip_along(5, 0.5, |t| {
            let t = t.min(1.5);
            ([3.0 * t - t * t, 0.0], [3.0 - 2.0 * t, 0.0])
        });
        let [_, ca, _, ct] = clip_errors(&c, 3, None);
        assert_eq!((ca.len(), ct.len()), (1, 1));
        assert!((ca[0] - 0.25).abs() < 1e-9, "{ca:?}");
        assert!(ct[0] < 1e-3, "{ct:?}");
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
