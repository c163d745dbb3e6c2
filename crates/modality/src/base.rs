//! The [`Modality`] trait: one implementation per kind of scene content.

use crate::error::Result;
use crate::mark::Mark;
use crate::scalar::ClampCount;
use crate::spec::{Codebook, ModalitySpec};
use umgen_scene::{Frame, SceneClip};

/// What decoding one frame's tokens found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DecodeReport {
    /// Token groups that made no sense and were skipped (an agent slot mixing pad and value ids, say).
    pub malformed: u64,
}

/// One kind of scene content, turned into a fixed number of tokens per frame and back.
///
/// A modality reads its own part of a [`Frame`]: the built-in ones read `action`, `agents`, `map` or
/// `image`; new ones read [`Frame::extras`] under their own key. Decoding writes that part back, so that
/// `detokenize(tokenize(frame))` reproduces the frame's content up to the tokenizer's resolution.
///
/// Implementations must be deterministic: the same clip gives the same ids.
pub trait Modality: Send + Sync + std::fmt::Debug {
    /// Name, vocabulary, tokens per frame, special ids and grid.
    fn spec(&self) -> &ModalitySpec;

    /// Tokenizer settings that change what ids mean (ranges, bin counts, codebook identity). They enter
    /// the frame layout's fingerprint, so a checkpoint never meets tokens it was not trained on.
    fn settings(&self) -> serde_json::Value {
        serde_json::Value::Null
    }

    /// The content ids of frame `t` of `clip`: exactly `tokens_per_frame` ids below `vocab_size`.
    ///
    /// The whole clip is given because some modalities need context (agent slots stay fixed per track).
    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>>;

    /// The ids of every frame of a clip. Override it when per-clip work (slot assignment, batched
    /// encoding) can be shared between frames.
    fn tokenize_clip(&self, clip: &SceneClip) -> Result<Vec<Vec<u32>>> {
        (0..clip.len()).map(|t| self.tokenize(clip, t)).collect()
    }

    /// Writes the values that `ids` (one frame's content ids) stand for into this modality's part of
    /// `frame`.
    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport>;

    /// A pre-trained embedding for the content ids, when the modality has one (VQ codebooks).
    fn codebook(&self) -> Option<&Codebook> {
        None
    }

    /// Values clamped into range since the modality was built, per field.
    fn clamp_report(&self) -> Vec<ClampCount> {
        Vec::new()
    }

    /// What `umgen viz` draws for this modality's part of `frame` on the bird's-eye view, over the map
    /// and agents. The built-in content (map, agents, ego, camera) is drawn by viz itself; a modality
    /// that reads [`Frame::extras`] returns its marks here so that pictures show it.
    fn marks(&self, frame: &Frame) -> Vec<Mark> {
        let _ = frame;
        Vec::new()
    }
}
