//! Frames and clips.

use crate::agent::Agent;
use crate::error::{Result, SceneError};
use crate::network::RoadNetwork;
use crate::pose::{EgoAction, EgoPose};
use crate::raster::{CameraImage, MapRaster};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Data of a modality the built-in fields do not cover, stored under the modality's own key in
/// [`Frame::extras`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "type", content = "values")]
pub enum Extra {
    /// Real values.
    F32(Vec<f32>),
    /// Integers.
    I64(Vec<i64>),
    /// Bytes.
    U8(Vec<u8>),
    /// Text.
    Text(String),
}

/// Everything known about the scene at one time step.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Frame {
    /// Seconds since the start of the clip.
    pub time: f64,
    /// Global ego pose.
    pub ego: EgoPose,
    /// Ego motion since the previous frame, in the previous ego frame.
    pub action: EgoAction,
    /// Agents in this frame's ego coordinates.
    pub agents: Vec<Agent>,
    /// Rendered BEV map raster, when present.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<MapRaster>,
    /// Rendered front camera image, when present.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<CameraImage>,
    /// Data of further modalities, keyed by the modality's name.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub extras: BTreeMap<String, Extra>,
}

/// A sequence of frames at a fixed interval.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneClip {
    /// Clip id, unique within a dataset.
    pub id: String,
    /// Seconds between consecutive frames.
    pub interval: f64,
    /// The frames, in time order.
    pub frames: Vec<Frame>,
    /// The road network the clip was recorded on, when known; views are rendered from it.
    #[serde(skip)]
    pub network: Option<Arc<RoadNetwork>>,
}

impl SceneClip {
    /// A clip of frames; see [`SceneClip::validate`].
    pub fn new(id: impl Into<String>, interval: f64, frames: Vec<Frame>) -> Result<Self> {
        let clip = Self {
            id: id.into(),
            interval,
            frames,
            network: None,
        };
        clip.validate()?;
        Ok(clip)
    }

    /// The same clip on a road network.
    pub fn with_network(mut self, network: Arc<RoadNetwork>) -> Self {
        self.network = Some(network);
        self
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the clip has no frames.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Frame `t`, or an error naming the clip.
    pub fn frame(&self, t: usize) -> Result<&Frame> {
        self.frames.get(t).ok_or_else(|| SceneError::FrameOutOfRange {
            clip: self.id.clone(),
            len: self.len(),
            index: t,
        })
    }

    /// Checks the interval, the frame times and that every pose, action and agent value is finite.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| {
            Err(SceneError::InvalidClip {
                clip: self.id.clone(),
                reason,
            })
        };
        if !(self.interval.is_finite() && self.interval > 0.0) {
            return bad(format!("frame interval {} s is not positive", self.interval));
        }
        for (t, f) in self.frames.iter().enumerate() {
            let ego = [
                f.time,
                f.ego.x,
                f.ego.y,
                f.ego.heading,
                f.ego.speed,
                f.action.dx,
                f.action.dy,
                f.action.dtheta,
            ];
            if ego.iter().any(|v| !v.is_finite()) {
                return bad(format!("frame {t}: non-finite ego pose, action or time"));
            }
            if t > 0 && f.time <= self.frames[t - 1].time {
                return bad(format!("frame {t}: time {} s does not increase", f.time));
            }
            for a in &f.agents {
                let v = [
                    a.x, a.y, a.z, a.vx, a.vy, a.vz, a.heading, a.length, a.width, a.height,
                ];
                if v.iter().any(|x| !x.is_finite()) {
                    return bad(format!(
                        "frame {t}: agent track {} has a non-finite value",
                        a.track_id
                    ));
                }
            }
        }
        Ok(())
    }

    /// Sets every frame's action from the poses of it and its predecessor. Frame 0 keeps its action,
    /// which only the data source can know.
    pub fn recompute_actions(&mut self) {
        for t in 1..self.frames.len() {
            let prev = self.frames[t - 1].ego.pose2();
            let next = self.frames[t].ego.pose2();
            self.frames[t].action = EgoAction::between(&prev, &next);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(t: f64, x: f64) -> Frame {
        Frame {
            time: t,
            ego: EgoPose {
                x,
                y: 0.0,
                heading: 0.0,
                speed: 4.0,
            },
            ..Frame::default()
        }
    }

    #[test]
    fn recompute_actions_from_poses() {
        let mut clip =
            SceneClip::new("c", 0.5, vec![frame(0.0, 0.0), frame(0.5, 2.0), frame(1.0, 4.5)]).unwrap();
        clip.recompute_actions();
        assert_eq!(clip.frames[0].action, EgoAction::default());
        assert!((clip.frames[1].action.dx - 2.0).abs() < 1e-12);
        assert!((clip.frames[2].action.dx - 2.5).abs() < 1e-12);
    }

    #[test]
    fn validation_names_the_problem() {
        let err = SceneClip::new("c7", 0.0, vec![frame(0.0, 0.0)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("c7") && err.contains("interval"), "{err}");
        let err = SceneClip::new("c8", 0.5, vec![frame(0.0, 0.0), frame(0.0, 1.0)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("frame 1") && err.contains("increase"), "{err}");
        let err = SceneClip::new("c9", 0.5, vec![frame(0.0, f64::NAN)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("non-finite"), "{err}");
        let clip = SceneClip::new("c", 0.5, vec![frame(0.0, 0.0)]).unwrap();
        assert!(
            clip.frame(1)
                .unwrap_err()
                .to_string()
                .contains("frame 1 does not exist")
        );
    }

    #[test]
    fn frames_round_trip_through_json_with_extras() {
        let mut f = frame(0.0, 1.0);
        f.extras.insert("lights".into(), Extra::U8(vec![0, 1, 2]));
        f.map = Some(MapRaster::zeros(1, 2, 2));
        let s = serde_json::to_string(&f).unwrap();
        assert_eq!(serde_json::from_str::<Frame>(&s).unwrap(), f);
    }
}
