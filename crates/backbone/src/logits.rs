//! The logits of teacher-forced windows, head by head: what outside runners of an export bundle are
//! checked against (`umgen export --golden`).

use crate::error::Result;
use crate::model::Backbone;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};
use umgen_ops::Kernels;

/// Every head's logits for windows of `b` × (`t` + 1) frames (frame `i + 1` predicted from frames
/// `0..=i`), as [`Backbone::loss`] scores them.
#[derive(Debug, Clone)]
pub struct ForcedLogits<B: Backend> {
    /// Per segment, in frame order: the TAR head's logits `[b, t, tokens, vocab]`.
    pub tar: Vec<Tensor<B, 4>>,
    /// Per segment: the OAR head's logits `[b, t, tokens, vocab]`.
    pub oar: Vec<Tensor<B, 4>>,
    /// The ego module's logits of the next action `[b, t, q, vocab]`, when the model has one.
    pub ego: Option<Tensor<B, 4>>,
}

impl<B: Backend> Backbone<B> {
    /// The logits of every head for windows `tokens` `[b, t + 1, N]` (t ≥ 1), teacher-forced: the OAR
    /// reads the target frame's tokens, the TAR and the ego module the conditioning frames, AMA and the
    /// tracked slots the target frames' actions. Dropout is off in inference models.
    pub fn forced_logits(&self, tokens: Tensor<B, 3, Int>) -> Result<ForcedLogits<B>> {
        let [b, f, _] = tokens.dims();
        let t = f.saturating_sub(1);
        let k = &Kernels::DEFAULT;
        let fwd = self.teacher_forced(tokens, 0.0, k, None)?;
        let per_segment = |heads: &crate::Heads<B>, x: &Tensor<B, 3>| {
            (0..self.spec().segments.len())
                .map(|s| {
                    let l = heads.logits(s, x.clone(), k);
                    let [_, tokens, v] = l.dims();
                    l.reshape([b, t, tokens, v])
                })
                .collect()
        };
        Ok(ForcedLogits {
            tar: per_segment(&self.tar_heads, &fwd.h),
            oar: per_segment(&self.oar_heads, &fwd.o),
            ego: self.ego_logits(fwd.e, false),
        })
    }
}
