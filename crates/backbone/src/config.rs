//! Sizes of the backbone (`[backbone]` in configs).

use serde::{Deserialize, Serialize};
pub use umgen_ops::Precision;

/// Widths, depths and regularisation of the backbone. Defaults are the paper's (supplementary Table).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BackboneConfig {
    /// Model width D.
    pub d_model: usize,
    /// Attention heads (D must divide by it).
    pub heads: usize,
    /// Width E of token embeddings before the embedding MLP (0 = D).
    pub embed_dim: usize,
    /// MLP hidden width as a multiple of D.
    pub mlp_ratio: usize,
    /// Dropout on embeddings, attention outputs and MLP outputs (training only).
    pub dropout: f64,
    /// Cross-attention layers over the ego history (CA_hist).
    pub ego_hist_layers: usize,
    /// Cross-attention layers over the current environment (CA_env).
    pub ego_env_layers: usize,
    /// TAR blocks (each a temporal causal layer and a spatial bidirectional layer).
    pub tar_layers: usize,
    /// OAR causal layers.
    pub oar_layers: usize,
    /// Longest window the frame (time) embedding covers.
    pub max_frames: usize,
    /// The modality whose tokens are the ego action (predicted by the ego module, decoded for AMA);
    /// `""` for none.
    pub action: Option<String>,
    /// The metric-grid modality that AMA moves by the ego action; `""` turns AMA off.
    pub align: Option<String>,
    /// Add to the ego module's queries of each frame the embedding of that frame's own action (the
    /// motion that led to it): the history it attends to carries no time, so without it the module
    /// cannot tell the latest motion from older ones, and "keep going" is hard to learn. `false` is
    /// the paper's module.
    pub ego_last: bool,
    /// The modality whose slots of tracked objects the TAR also sees moved one frame ahead (each moved
    /// by its own velocity and then into the next ego frame by the ego action, [`crate::track`]);
    /// `""` or absent turns it off.
    pub track: Option<String>,
    /// Move `track`'s slots by constant acceleration (the velocity's change since the window's previous
    /// frame kept for one more frame) instead of constant velocity. Needs `track`.
    pub track_accel: bool,
    /// Brake `track`'s slots for a slower object ahead in their lane ([`crate::FollowSpec`]'s rule: the
    /// deceleration that matches its speed before the gap closes): a moved slot otherwise carries its
    /// motion on into a queue, and braking that has not begun is what a model copying its hint never
    /// learns. Needs `track`. Left out of saved configs when off, so that manifests without it read as
    /// before.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub track_follow: bool,
    /// The modality whose slots are stop points (a traffic light's stop lines, declared by the modality)
    /// that `track_follow` brakes for as standing objects while they ask to stop
    /// ([`crate::StopSpec`]): braking for a red light becomes part of the hint instead of a departure
    /// the model must learn from lights it sees only as tokens. Needs `track_follow`. `""` or absent
    /// turns it off; left out of saved configs when off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub track_stops: Option<String>,
    /// Seconds between consecutive frames of a training window or a rollout (`train.gap` × the data's
    /// frame interval): how far `track` moves an object at its velocity. Training and generation refuse
    /// data that steps otherwise.
    pub step_s: f64,
    /// Number format of the matrix products (`f32`, or `bf16` with f32 master weights; `umgen_ops::format`).
    pub precision: Precision,
    /// Start the embedding and output-head rows of ordered value bins (segments with
    /// [`ordinal`](crate::SegmentSpec::ordinal) ids: the ego action, the agents' values) as a sinusoid
    /// of the bin index, so that neighbouring bins begin close and what is learnt for one value carries
    /// over to its neighbours; `false` draws them at random like every other row. Initialisation only:
    /// checkpoints do not depend on it.
    pub ordinal_init: bool,
}

impl Default for BackboneConfig {
    fn default() -> Self {
        Self {
            d_model: 768,
            heads: 12,
            embed_dim: 0,
            mlp_ratio: 4,
            dropout: 0.15,
            ego_hist_layers: 12,
            ego_env_layers: 12,
            tar_layers: 24,
            oar_layers: 24,
            max_frames: 32,
            action: Some("ego".into()),
            align: Some("map".into()),
            ego_last: false,
            track: None,
            track_accel: false,
            track_follow: false,
            track_stops: None,
            step_s: 0.5,
            precision: Precision::F32,
            ordinal_init: true,
        }
    }
}

impl BackboneConfig {
    /// The first setting no model can use, as (key under `[backbone]`, what is wrong with its value);
    /// `None` when every one is usable. Layout-dependent checks (heads dividing the width, segments) come
    /// later, in [`crate::BackboneSpec::validate`].
    pub fn problem(&self) -> Option<(&'static str, String)> {
        if !(0.0..1.0).contains(&self.dropout) {
            return Some((
                "dropout",
                format!("{} must be a probability below 1", self.dropout),
            ));
        }
        if !(self.step_s.is_finite() && self.step_s > 0.0) {
            return Some((
                "step_s",
                format!("{} must be a positive number of seconds", self.step_s),
            ));
        }
        let at_least_one = [
            ("d_model", self.d_model),
            ("heads", self.heads),
            ("mlp_ratio", self.mlp_ratio),
            ("max_frames", self.max_frames),
        ];
        at_least_one
            .into_iter()
            .find(|(_, v)| *v == 0)
            .map(|(key, v)| (key, format!("{v} must be 1 or more")))
    }

    /// The settings generation builds the model with: products in f32 whatever `precision` trained it
    /// (the parameters are f32 either way). Without autotuning, burn's bf16 matmul kernel is no faster than
    /// its f32 one on generation's shapes and the casts would come on top (docs/performance.md).
    pub fn for_inference(&self) -> BackboneConfig {
        BackboneConfig {
            precision: Precision::F32,
            ..self.clone()
        }
    }

    /// Embedding width E.
    pub fn embed(&self) -> usize {
        if self.embed_dim == 0 {
            self.d_model
        } else {
            self.embed_dim
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inference_computes_in_f32_and_keeps_every_other_setting() {
        let trained = BackboneConfig {
            precision: Precision::Bf16Linear,
            d_model: 64,
            tar_layers: 3,
            ..BackboneConfig::default()
        };
        let inference = trained.for_inference();
        assert_eq!(inference.precision, Precision::F32);
        assert_eq!(
            BackboneConfig {
                precision: Precision::Bf16Linear,
                ..inference
            },
            trained
        );
    }
}
