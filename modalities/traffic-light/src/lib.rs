//! A fifth modality for umgen, written the way a user writes one: outside the built-in crates, against the
//! public [`Modality`](umgen::modality::Modality) trait only.
//!
//! It tokenizes the traffic-signal heads nearest to the ego, as `umgen data sumo --tls` stores them in
//! each frame (`extras["signals"]`: x, y, heading and state code per head, nearest first): `count` slots
//! of four tokens, `x, y, heading` in `bins` uniform bins each (ids `0..bins`) and the state
//! (`bins + 0..4`: off, red, yellow, green); an empty slot is four pad tokens (`bins + 4`). Decoding writes
//! the heads back under the same key, so generated frames carry light states, and
//! [`marks`](umgen::modality::Modality::marks) draws them on `umgen viz` pictures.
//!
//! [`crossings`] counts vehicles crossing stop lines by the light's state, recorded or generated: whether
//! agents stop at red.
//!
//! The crate's binary, `umgen-lights`, is every `umgen` command with this kind registered
//! (`umgen_cli::App`); `docs/adding-a-modality.md` walks through both.

mod config;
pub mod crossings;
mod modality;

pub use config::{SLOT, TrafficLightConfig, VALUE_FIELDS};
pub use modality::{Head, KIND, TrafficLight, colour};
