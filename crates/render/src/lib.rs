//! Deterministic views of a road network around an ego pose.
//!
//! - [`MapView`] rasterises the six map layers (lane, stop line, crosswalk, intersection, lane divider,
//!   lane connector) into a C×H×W [`MapRaster`](umgen_scene::MapRaster) centred on the ego, row 0 at the
//!   front and column 0 at the left (paper default: 128 m, 256×256, 0.5 m per pixel).
//! - [`Camera`] renders a pinhole front view: ground from the map geometry (road, sidewalks, markings,
//!   zebra crossings), sky, and agents as shaded 3D boxes coloured by category.
//! - [`Canvas`] is the scanline rasteriser both use (pixel-centre sampling, even-odd rule).
//! - [`MapMemory`] holds what map rasters showed in cells fixed in the world, so that a rollout's map
//!   reads the same ground the same way from every later pose.
//!
//! ```
//! use umgen_render::MapView;
//! use umgen_scene::{MapLayer, Pose2, RoadNetwork};
//! // A 4 m wide lane along the ego's heading, from 20 m behind to 40 m ahead.
//! let net = RoadNetwork { lanes: vec![vec![[-20.0, -2.0], [40.0, -2.0], [40.0, 2.0], [-20.0, 2.0]]], ..Default::default() };
//! let raster = MapView::default().render(&net, &Pose2::default());
//! let lane = MapLayer::Lane.channel();
//! assert_eq!(raster.get(lane, 128 - 20, 128), Some(255)); // 10 m ahead, on the centre line
//! assert_eq!(raster.get(lane, 128 - 20, 128 - 10), Some(0)); // 5 m to the left: off the lane
//! ```

mod camera;
mod fill;
mod map;
mod memory;
mod palette;

pub use camera::Camera;
pub use fill::Canvas;
pub use map::MapView;
pub use memory::{MapMemory, MemoryError};
pub use palette::{Class, agent as agent_colour};
