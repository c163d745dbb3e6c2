//! Importing Eclipse SUMO simulations.
//!
//! [`import`] reads a network (`.net.xml`: lanes with shapes and widths, internal lanes, crossings,
//! walking areas, junction shapes and types), vehicle types (`<vType>` in route files, plus SUMO's
//! built-in defaults) and an FCD trace (`--fcd-output`), checks that the trace runs on that network, and
//! adds a log, the network and one clip per ego vehicle trajectory piece to a dataset.

mod fcd;
mod geometry;
mod import;
mod net;
mod tls;
mod types;
mod xml;

pub use fcd::{Fcd, parse_fcd};
pub use geometry::{offset, strip};
pub use import::{EGO_CLASSES, ImportOptions, ImportReport, import};
pub use net::{SumoNet, parse_net};
pub use tls::{parse_heads, parse_states};
pub use types::{TypeInfo, TypeTable, class_category, class_defaults};
