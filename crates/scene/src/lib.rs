//! Plain driving-scene data for umgen, with no tensors and no I/O.
//!
//! A [`SceneClip`] is a sequence of [`Frame`]s sampled at a fixed interval. Each frame holds the ego
//! vehicle's global pose ([`EgoPose`]), its motion since the previous frame ([`EgoAction`], expressed in the
//! previous ego frame), the traffic [`Agent`]s in the current ego frame, and optional rendered views: the map
//! raster ([`MapRaster`], C×H×W) and the front camera image ([`CameraImage`], 3×H×W, u8). Modalities that the
//! built-in types do not cover keep their data in [`Frame::extras`], so adding one never edits this crate.
//!
//! The road network around a clip is a [`RoadNetwork`] of vector geometry (lanes, connectors, crossings,
//! junctions, stop lines, dividers, sidewalks), shared by the clips recorded on it.
//!
//! Coordinates: the ego frame has x forward, y left, z up; headings are counter-clockwise from +x in
//! radians, wrapped to [-π, π). [`Pose2`] moves points, headings and velocities between frames.
//!
//! ```
//! use umgen_scene::{EgoAction, Pose2};
//! let prev = Pose2::new(10.0, 5.0, std::f64::consts::FRAC_PI_2);
//! let next = prev.apply(&EgoAction::new(2.0, 0.0, 0.0));
//! assert!((next.y - 7.0).abs() < 1e-12); // driving "forward" while facing +y
//! let action = EgoAction::between(&prev, &next);
//! assert!((action.dx - 2.0).abs() < 1e-12);
//! ```

mod agent;
mod error;
mod frame;
mod network;
mod pose;
mod raster;

pub use agent::{Agent, AgentCategory};
pub use error::{Result, SceneError};
pub use frame::{Extra, Frame, SceneClip};
pub use network::{
    Bounds, Crosswalk, MapLayer, Marking, Polygon, Polyline, RoadNetwork, bbox, boxes_overlap,
};
pub use pose::{EgoAction, EgoPose, Pose2, wrap_angle};
pub use raster::{CameraImage, MapRaster};
