//! What [`Backbone::loss_with`](crate::Backbone::loss_with) takes besides the tokens, and what it
//! returns.

use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// Per-modality losses of one batch, each a mean over that modality's tokens, and their total.
#[derive(Debug, Clone)]
pub struct Losses<B: Backend> {
    /// `CE(OAR) + CE(TAR) + ego_weight · CE(ego)`, the first two averaged over all content tokens.
    pub total: Tensor<B, 1>,
    /// Named parts: `oar`, `tar`, `ego`, and `oar/<label>`, `tar/<label>` per segment.
    pub parts: Vec<(String, Tensor<B, 1>)>,
}

/// Options of [`Backbone::loss_with`](crate::Backbone::loss_with).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossOptions {
    /// Weight of the ego-action cross-entropy.
    pub ego_weight: f64,
    /// Probability that a predicted frame's OAR is trained without its TAR prior, which is how
    /// `umgen generate --from-scratch` runs it (0 = never).
    pub prior_drop: f64,
    /// Spread in bins of the targets of ordered value bins (agents' values, the ego action); 0 scores
    /// the target bin alone. See [`crate::smoothing`].
    pub ordinal_sigma: f64,
}

impl LossOptions {
    /// What is wrong with these options, as `key = value …` (the keys are those of `[train]`); `None` if
    /// nothing is.
    pub fn problem(&self) -> Option<String> {
        if !(0.0..=1.0).contains(&self.prior_drop) {
            return Some(format!(
                "prior_drop = {} must be a probability (0 to 1)",
                self.prior_drop
            ));
        }
        if !(self.ordinal_sigma.is_finite() && self.ordinal_sigma >= 0.0) {
            return Some(format!(
                "ordinal_sigma = {} must be a spread in bins, 0 or more",
                self.ordinal_sigma
            ));
        }
        None
    }
}
