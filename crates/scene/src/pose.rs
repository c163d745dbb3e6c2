//! Rigid 2D poses (SE(2)), the ego pose and the ego action.

use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

/// Wraps an angle in radians to [-π, π).
pub fn wrap_angle(a: f64) -> f64 {
    let w = (a + PI).rem_euclid(TAU) - PI;
    // rem_euclid can round up to exactly TAU for tiny negative inputs.
    if w >= PI { w - TAU } else { w }
}

/// A rigid 2D pose: position and heading (counter-clockwise from +x, radians).
///
/// A pose is also the transform from its own local frame (x forward, y left) to the frame it is expressed
/// in: [`Pose2::to_parent`] maps local points out, [`Pose2::to_local`] maps points in.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose2 {
    /// x position (metres).
    pub x: f64,
    /// y position (metres).
    pub y: f64,
    /// Heading (radians).
    pub heading: f64,
}

impl Pose2 {
    /// A pose from position and heading; the heading is wrapped to [-π, π).
    pub fn new(x: f64, y: f64, heading: f64) -> Self {
        Self {
            x,
            y,
            heading: wrap_angle(heading),
        }
    }

    /// Maps a point given in this pose's local frame to the parent frame.
    pub fn to_parent(&self, p: [f64; 2]) -> [f64; 2] {
        let v = self.rotate_to_parent(p);
        [self.x + v[0], self.y + v[1]]
    }

    /// Maps a point given in the parent frame into this pose's local frame.
    pub fn to_local(&self, p: [f64; 2]) -> [f64; 2] {
        self.rotate_to_local([p[0] - self.x, p[1] - self.y])
    }

    /// Rotates a free vector (a velocity, say) from the local frame to the parent frame.
    pub fn rotate_to_parent(&self, v: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.heading.sin_cos();
        [c * v[0] - s * v[1], s * v[0] + c * v[1]]
    }

    /// Rotates a free vector from the parent frame into the local frame.
    pub fn rotate_to_local(&self, v: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.heading.sin_cos();
        [c * v[0] + s * v[1], -s * v[0] + c * v[1]]
    }

    /// `self ∘ other`: `other` is given in this pose's local frame; the result is in the parent frame.
    pub fn compose(&self, other: &Pose2) -> Pose2 {
        let [x, y] = self.to_parent([other.x, other.y]);
        Pose2::new(x, y, self.heading + other.heading)
    }

    /// The inverse transform: this pose's parent frame expressed in its local frame.
    pub fn inverse(&self) -> Pose2 {
        let [x, y] = self.rotate_to_local([-self.x, -self.y]);
        Pose2::new(x, y, -self.heading)
    }

    /// `other` (given in the parent frame) expressed in this pose's local frame.
    pub fn relative(&self, other: &Pose2) -> Pose2 {
        let [x, y] = self.to_local([other.x, other.y]);
        Pose2::new(x, y, other.heading - self.heading)
    }

    /// The pose reached by applying an ego action (a motion expressed in this pose's frame).
    pub fn apply(&self, action: &EgoAction) -> Pose2 {
        self.compose(&Pose2 {
            x: action.dx,
            y: action.dy,
            heading: action.dtheta,
        })
    }
}

/// The ego vehicle's global pose and speed at one frame.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct EgoPose {
    /// Global x (metres).
    pub x: f64,
    /// Global y (metres).
    pub y: f64,
    /// Global heading (radians, [-π, π)).
    pub heading: f64,
    /// Speed along the heading (m/s).
    pub speed: f64,
}

impl EgoPose {
    /// The rigid part of the pose.
    pub fn pose2(&self) -> Pose2 {
        Pose2::new(self.x, self.y, self.heading)
    }

    /// The pose after an action over one frame interval of `dt` seconds; the speed is the travelled
    /// distance over `dt` (the best estimate an action alone gives).
    pub fn advance(&self, action: &EgoAction, dt: f64) -> EgoPose {
        let p = self.pose2().apply(action);
        let dist = action.dx.hypot(action.dy);
        let speed = if dt > 0.0 { dist / dt } else { self.speed };
        EgoPose {
            x: p.x,
            y: p.y,
            heading: p.heading,
            speed,
        }
    }
}

/// The ego motion from the previous frame to this one, expressed in the previous ego frame.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct EgoAction {
    /// Forward displacement (metres).
    pub dx: f64,
    /// Leftward displacement (metres).
    pub dy: f64,
    /// Heading change (radians, [-π, π)).
    pub dtheta: f64,
}

impl EgoAction {
    /// An action from its three components.
    pub fn new(dx: f64, dy: f64, dtheta: f64) -> Self {
        Self { dx, dy, dtheta }
    }

    /// The action that moves `prev` onto `next`.
    pub fn between(prev: &Pose2, next: &Pose2) -> Self {
        let r = prev.relative(next);
        Self {
            dx: r.x,
            dy: r.y,
            dtheta: r.heading,
        }
    }

    /// The components as an array `[dx, dy, dtheta]`.
    pub fn to_array(&self) -> [f64; 3] {
        [self.dx, self.dy, self.dtheta]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-9
    }

    fn close_angle(a: f64, b: f64) -> bool {
        wrap_angle(a - b).abs() < 1e-9
    }

    #[test]
    fn wrap_angle_range() {
        assert!(close(wrap_angle(PI), -PI));
        assert!(close(wrap_angle(3.0 * PI / 2.0), -PI / 2.0));
        assert!(close(wrap_angle(-3.0 * PI / 2.0), PI / 2.0));
        assert!(close(wrap_angle(0.1 + 4.0 * TAU), 0.1));
        for a in [-1e-17, 1e-17, -PI, PI - 1e-15] {
            let w = wrap_angle(a);
            assert!((-PI..PI).contains(&w), "{a} -> {w}");
        }
    }

    #[test]
    fn hand_computed_transform() {
        // Ego at (10, 5) facing +y: a point 3 m ahead and 1 m to the left is at (9, 8).
        let ego = Pose2::new(10.0, 5.0, PI / 2.0);
        let g = ego.to_parent([3.0, 1.0]);
        assert!(close(g[0], 9.0) && close(g[1], 8.0), "{g:?}");
        let l = ego.to_local(g);
        assert!(close(l[0], 3.0) && close(l[1], 1.0));
        // A global velocity along +x is to the ego's right (negative y).
        let v = ego.rotate_to_local([2.0, 0.0]);
        assert!(close(v[0], 0.0) && close(v[1], -2.0), "{v:?}");
    }

    #[test]
    fn compose_inverse_and_relative_are_consistent() {
        let mut rng = StdRng::seed_from_u64(7);
        for _ in 0..200 {
            let a = Pose2::new(
                rng.random_range(-100.0..100.0),
                rng.random_range(-100.0..100.0),
                rng.random_range(-4.0..4.0),
            );
            let b = Pose2::new(
                rng.random_range(-100.0..100.0),
                rng.random_range(-100.0..100.0),
                rng.random_range(-4.0..4.0),
            );
            let id = a.compose(&a.inverse());
            assert!(close(id.x, 0.0) && close(id.y, 0.0) && close_angle(id.heading, 0.0));
            let back = a.compose(&a.relative(&b));
            assert!(close(back.x, b.x) && close(back.y, b.y) && close_angle(back.heading, b.heading));
            let act = EgoAction::between(&a, &b);
            let reached = a.apply(&act);
            assert!(
                close(reached.x, b.x) && close(reached.y, b.y) && close_angle(reached.heading, b.heading)
            );
        }
    }

    #[test]
    fn advance_integrates_actions() {
        let start = EgoPose {
            x: 0.0,
            y: 0.0,
            heading: 0.0,
            speed: 0.0,
        };
        // Four quarter turns with forward steps trace a closed square-ish loop back to the start heading.
        let mut p = start;
        for _ in 0..4 {
            p = p.advance(&EgoAction::new(5.0, 0.0, PI / 2.0), 0.5);
        }
        assert!(
            close(p.x, 0.0) && close(p.y, 0.0) && close_angle(p.heading, 0.0),
            "{p:?}"
        );
        assert!(close(p.speed, 10.0));
    }
}
