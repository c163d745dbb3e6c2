//! Scene generation with a trained umgen backbone.
//!
//! [`Generator::next_frame`] makes one new frame for a batch of scenes: the ego module proposes the
//! action (or a [`FrameControl`] forces it), the TAR runs over the last ≤ `window` frames (20 in the paper;
//! older frames slide out, so rollouts can be arbitrarily long), and the OAR fills the frame token by token
//! over a key/value cache, each modality sampled with its own [`Sampling`] (top-k, top-p, temperature,
//! seeded). Without history (`t = 0`) the TAR is skipped and an initial scene is generated from nothing.
//!
//! [`engine::Engine`] makes the same frames from the model's weights alone, as a fixed program of
//! operations: on a GPU each decoding step is one replayed CUDA graph and the host reads the frame back
//! once; on the host it is the reference the GPU is checked against. Both implement [`NextFrame`].

mod boxes;
mod control;
mod device_draw;
pub mod engine;
mod error;
mod road;
mod rollout;
mod rules;
mod sampling;

pub use boxes::GroupBoxes;
pub use control::{AgentControl, Control, EgoControl};
pub use device_draw::DeviceTopK;
pub use error::{GenerateError, Result};
pub use road::{Area, Entering, RoadCount, RoadRule};
pub use rollout::{
    DEFAULT_PASS_FRAMES, DEFAULT_UNIFORM_BLOCK, FrameControl, Generator, GivenSegment, TokenGroups,
};
pub use sampling::Sampling;

/// What makes frames: the burn decoder ([`Generator`]) or the engine ([`engine::Engine`]).
pub trait NextFrame {
    /// The next frame `[m][N]` of each of `m` scenes from their histories `[m][t][N]` (all of one length;
    /// `t = 0` makes initial scenes), under `control`.
    fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>>;

    /// New agents the new-agent rule tested so far, and how many it dropped.
    fn new_agents(&self) -> (u64, u64);
}

impl<B: burn::tensor::backend::Backend> NextFrame for Generator<'_, B> {
    fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>> {
        Generator::next_frame(self, history, control)
    }

    fn new_agents(&self) -> (u64, u64) {
        Generator::new_agents(self)
    }
}

impl<X: umgen_cuda::Exec> NextFrame for engine::Engine<X> {
    fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>> {
        engine::Engine::next_frame(self, history, control)
    }

    fn new_agents(&self) -> (u64, u64) {
        engine::Engine::new_agents(self)
    }
}
