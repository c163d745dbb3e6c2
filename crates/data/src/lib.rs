//! umgen datasets: the on-disk format, window reading, statistics and importers.
//!
//! A dataset is a directory:
//!
//! ```text
//! index.json            networks, logs, clips, per-modality statistics (see `Index`)
//! networks/<id>.json    road network geometry (lanes, connectors, crossings, …), shared by many clips
//! logs/<id>.ulog        every actor's state at every step of one recording (see `log`)
//! logs/<id>.signals.json  where its traffic signals stand and their states over its steps (optional,
//!                       see `signals`)
//! ```
//!
//! What is stored is compact and true: actor states in global coordinates and vector road geometry. A clip
//! is one ego track over a range of steps; frames are cut from logs on demand (`Dataset::read_window`):
//! the ego pose and action, and the agents within the view in the ego's frame. Map rasters and camera
//! images are rendered from the network around the ego pose (crate `umgen-render`), never stored.
//! `docs/data-format.md` describes the format byte by byte.
//!
//! The [`sumo`] module imports Eclipse SUMO networks and FCD traces, and traffic-light states.

mod dataset;
mod error;
mod index;
pub mod log;
mod scenes;
pub mod signals;
mod stats;
pub mod sumo;
mod tokens;
mod view;

pub use dataset::{Dataset, Window, load_network};
pub use error::{DataError, Result};
pub use index::{ClipEntry, INDEX_FILE, Index, LogEntry, NetworkEntry, SignalsEntry};
pub use log::{Log, LogShard, State, Track};
pub use scenes::{clip_log, write_scene_dataset};
pub use signals::{LightState, SIGNALS_KEY, SignalHead, Signals};
pub use stats::{Stats, Summary};
pub use tokens::{TOKENS_INDEX, TokenClip, TokenIndex, TokenSet, TokenShard};
pub use view::{ViewOptions, agent_in_frame, ego_pose, frames};
