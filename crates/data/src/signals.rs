//! Traffic signals of a log: where each signal head stands and its state at every step, stored beside the
//! log (`logs/<id>.signals.json`) and attached to frames as [`Frame::extras`]`["signals"]`.
//!
//! A head is one controlled connection of a junction (SUMO: a `linkIndex` of a traffic light), placed at
//! the stop line of the lane it leaves and facing along it. States are kept as changes per head (step,
//! state), so a log of thousands of steps and hundreds of heads stays small. In a frame the heads within the
//! view are listed nearest first, four values each in the ego's frame: x, y (m), heading (rad) and the
//! state code ([`LightState`]).

use crate::error::{Result, corrupt, io};
use crate::log::write_atomic;
use serde::{Deserialize, Serialize};
use std::path::Path;
use umgen_scene::{Extra, Frame, Pose2, wrap_angle};

/// The key of the heads in [`Frame::extras`].
pub const SIGNALS_KEY: &str = "signals";

/// A signal head's state, as its code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u8)]
pub enum LightState {
    /// Dark, blinking or unknown.
    Off = 0,
    /// Stop.
    Red = 1,
    /// Amber (also red and amber together).
    Yellow = 2,
    /// Go (with or without priority).
    Green = 3,
}

impl LightState {
    /// The state a SUMO state character stands for: `r` red, `y`/`Y` amber, `u` red and amber, `g`/`G`/`s`
    /// green (`s`: green after stopping), `o`/`O` off. `None` for another character.
    pub fn from_sumo(c: char) -> Option<Self> {
        Some(match c {
            'r' | 'R' => LightState::Red,
            'y' | 'Y' | 'u' => LightState::Yellow,
            'g' | 'G' | 's' => LightState::Green,
            'o' | 'O' => LightState::Off,
            _ => return None,
        })
    }

    /// The state of code `c`, [`LightState::Off`] for an unknown code.
    pub fn from_code(c: u8) -> Self {
        match c {
            1 => LightState::Red,
            2 => LightState::Yellow,
            3 => LightState::Green,
            _ => LightState::Off,
        }
    }
}

/// One signal head in global coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SignalHead {
    /// The traffic light (SUMO `tlLogic` id).
    pub tl: String,
    /// The controlled connection's index in the light's state string.
    pub link: usize,
    /// Stop-line position (m).
    pub x: f64,
    /// Stop-line position (m).
    pub y: f64,
    /// Direction of travel at the stop line (rad, counter-clockwise from +x).
    pub heading: f64,
}

/// The heads of a log and their states over its steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Signals {
    /// The heads.
    pub heads: Vec<SignalHead>,
    /// Per head, the steps at which its state changed and the new state's code, in step order; before
    /// the first change a head is off.
    pub changes: Vec<Vec<(u32, u8)>>,
}

impl Signals {
    /// The state of head `head` at step `step`.
    pub fn state(&self, head: usize, step: usize) -> LightState {
        let Some(changes) = self.changes.get(head) else {
            return LightState::Off;
        };
        let after = changes.partition_point(|&(s, _)| s as usize <= step);
        after
            .checked_sub(1)
            .map_or(LightState::Off, |i| LightState::from_code(changes[i].1))
    }

    /// The heads within `range` m (along both axes) of `ego` at step `step`, nearest first, as
    /// [`Frame::extras`] holds them: x, y, heading and state code per head, in the ego's frame.
    pub fn near(&self, ego: &Pose2, step: usize, range: f64) -> Vec<f32> {
        let (c, s) = (ego.heading.cos(), ego.heading.sin());
        let mut seen: Vec<(f64, [f32; 4])> = self
            .heads
            .iter()
            .enumerate()
            .filter_map(|(i, h)| {
                let (dx, dy) = (h.x - ego.x, h.y - ego.y);
                let (x, y) = (c * dx + s * dy, -s * dx + c * dy);
                if x.abs() > range || y.abs() > range {
                    return None;
                }
                let heading = wrap_angle(h.heading - ego.heading);
                let state = self.state(i, step) as u8;
                Some((x.hypot(y), [x as f32, y as f32, heading as f32, f32::from(state)]))
            })
            .collect();
        seen.sort_by(|a, b| a.0.total_cmp(&b.0));
        seen.into_iter().flat_map(|(_, v)| v).collect()
    }

    /// Attaches [`Self::near`] of each frame's ego at the frame's step (`steps[i]` for `frames[i]`).
    pub fn attach(&self, frames: &mut [Frame], steps: &[usize], range: f64) {
        for (f, &step) in frames.iter_mut().zip(steps) {
            let near = self.near(&f.ego.pose2(), step, range);
            f.extras.insert(SIGNALS_KEY.into(), Extra::F32(near));
        }
    }

    /// Writes it to `path` (JSON, atomically); its CRC32.
    pub fn save(&self, path: &Path) -> Result<u32> {
        let bytes = serde_json::to_vec(self).map_err(|e| corrupt(path, e.to_string()))?;
        write_atomic(path, &bytes)?;
        Ok(crc32fast::hash(&bytes))
    }

    /// Reads `path`, checking its CRC32 and that every head has its list of changes.
    pub fn load(path: &Path, crc32: u32) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(io(path))?;
        if crc32fast::hash(&bytes) != crc32 {
            return Err(corrupt(path, "checksum mismatch (the index holds another CRC32)"));
        }
        let s: Signals = serde_json::from_slice(&bytes).map_err(|e| corrupt(path, e.to_string()))?;
        if s.changes.len() != s.heads.len() {
            return Err(corrupt(
                path,
                format!("{} heads but {} lists of changes", s.heads.len(), s.changes.len()),
            ));
        }
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one_head() -> Signals {
        Signals {
            heads: vec![SignalHead {
                tl: "B".into(),
                link: 0,
                x: 100.0,
                y: -4.8,
                heading: 0.0,
            }],
            changes: vec![vec![(2, 1), (5, 3)]],
        }
    }

    #[test]
    fn a_head_is_off_before_its_first_state_then_keeps_each_state_until_it_changes() {
        let s = one_head();
        let states: Vec<LightState> = (0..7).map(|t| s.state(0, t)).collect();
        use LightState::*;
        assert_eq!(states, [Off, Off, Red, Red, Red, Green, Green]);
        assert_eq!(s.state(3, 4), Off, "an unknown head is off");
    }

    #[test]
    fn heads_are_seen_in_the_egos_frame_nearest_first_within_the_range() {
        let mut s = one_head();
        s.heads.push(SignalHead {
            tl: "B".into(),
            link: 1,
            x: 60.0,
            y: -1.6,
            heading: std::f64::consts::PI,
        });
        s.changes.push(vec![(0, 2)]);
        // The ego at (50, -4.8) heading +y: the first head 50 m to its right (x → -y), the second 10 m right.
        let ego = Pose2::new(50.0, -4.8, std::f64::consts::FRAC_PI_2);
        let near = s.near(&ego, 3, 80.0);
        assert_eq!(near.len(), 8);
        let close = |a: f32, b: f64| (f64::from(a) - b).abs() < 1e-4;
        assert!(close(near[0], 3.2) && close(near[1], -10.0), "{near:?}");
        assert!(
            close(near[2], std::f64::consts::FRAC_PI_2) && near[3] == 2.0,
            "{near:?}"
        );
        assert!(
            close(near[4], 0.0) && close(near[5], -50.0) && near[7] == 1.0,
            "{near:?}"
        );
        assert_eq!(s.near(&ego, 3, 20.0).len(), 4, "the far head is out of range");
    }

    #[test]
    fn a_damaged_file_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let path = dir.path().join("x.signals.json");
        let crc = one_head().save(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(Signals::load(&path, crc).ok(), Some(one_head()));
        let e = Signals::load(&path, crc ^ 1)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("x.signals.json") && e.contains("checksum"), "{e}");
    }
}
