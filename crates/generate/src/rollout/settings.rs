//! The generator's settings beyond the model and sampling: how the work is split and drawn. None
//! changes the distribution of the frames; some change which frames a seed draws (said on each).

use super::Generator;
use crate::device_draw::DeviceTopK;
use burn::tensor::backend::Backend;

impl<B: Backend> Generator<'_, B> {
    /// Run the window pass (ego module and TAR) over at most `frames` window frames at a time (at least one
    /// scene): its activations grow with scenes × window × N, while the OAR's per-token state is small.
    /// The frames drawn do not depend on it.
    pub fn pass_frames(mut self, frames: usize) -> Self {
        self.pass_frames = frames.max(1);
        self
    }

    /// Upload the uniform numbers of the device draws at most `floats` at a time (at least one position's
    /// worth), drawn ahead in position order: the frames drawn do not depend on it.
    pub fn uniform_block(mut self, floats: usize) -> Self {
        self.uniform_block = floats.max(1);
        self
    }

    /// Decode the positions without rules (map and image codes) in speculative blocks of up to `k`
    /// positions, drafted by the TAR heads and verified by one OAR pass each (`rollout/speculate.rs`); 0 or
    /// 1 decodes one position per OAR step. The frames have the same distribution either way, not the
    /// same draws.
    pub fn speculate(mut self, k: usize) -> Self {
        self.speculate = k;
        self
    }

    /// Speculative blocks run so far and the positions they decided (their ratio is the mean accepted
    /// run plus one).
    pub fn speculation(&self) -> (u64, u64) {
        self.speculated
    }

    /// New agents (groups filled in a slot that was empty in the previous frame) that the new-agent rule
    /// tested so far, and how many of them it dropped for overlapping a box decoded before them (or, with
    /// [`crate::GroupBoxes::whole_frame`], an old agent decoded after them) or for exceeding the frame's
    /// box budget.
    pub fn new_agents(&self) -> (u64, u64) {
        self.new_agents
    }

    /// How device draws find the top-k ([`DeviceTopK::Reduce`] only on backends with `argtopk`).
    pub fn device_top_k(mut self, top_k: DeviceTopK) -> Self {
        self.top_k = top_k;
        self
    }

    /// Draw the positions without rules (map and image codes) on the model's device
    /// ([`Sampling::draw_rows`]) and read them back once per frame, instead of reading every position's
    /// logits to the host. For GPUs, where each read waits for the device; on the CPU the host draw is
    /// cheaper. Either way, a seed gives the same frames each run.
    pub fn draw_on_device(mut self, yes: bool) -> Self {
        self.on_device = yes;
        self
    }
}
