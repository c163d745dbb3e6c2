//! Scene generation with a trained umgen backbone.
//!
//! [`Generator::next_frame`] makes one new frame for a batch of scenes: the ego module proposes the
//! action (or a [`FrameControl`] forces it), the TAR runs over the last ≤ `window` frames (20 in the paper;
//! older frames slide out, so rollouts can be arbitrarily long), and the OAR fills the frame token by token
//! over a key/value cache, each modality sampled with its own [`Sampling`] (top-k, top-p, temperature,
//! seeded). Without history (`t = 0`) the TAR is skipped and an initial scene is generated from nothing.

mod boxes;
mod control;
mod device_draw;
pub mod engine;
mod error;
mod rollout;
mod rules;
mod sampling;

pub use boxes::GroupBoxes;
pub use control::{AgentControl, Control, EgoControl};
pub use device_draw::DeviceTopK;
pub use error::{GenerateError, Result};
pub use rollout::{DEFAULT_PASS_FRAMES, DEFAULT_UNIFORM_BLOCK, FrameControl, Generator, TokenGroups};
pub use sampling::Sampling;
