//! What [`Backbone::loss_with`](crate::Backbone::loss_with) takes besides the tokens, and what it
//! returns.

use crate::error::{BackboneError, Result};
use crate::model::Backbone;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};
use umgen_ops::Kernels;
use umgen_ops::ready::ReadyPoints;

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
    /// the target bin alone. See `umgen_ops::smoothing`.
    pub ordinal_sigma: f64,
    /// The kernels every operation of the pass runs on (`[train.kernels]`).
    pub kernels: Kernels,
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

impl<B: Backend> Backbone<B> {
    /// The teacher-forced training loss of windows `[b, t + 1, N]`: frames `0..t` condition, frame
    /// `i + 1` is the target of frame `i`, all `t` predictions at once.
    pub fn loss(&self, tokens: Tensor<B, 3, Int>, ego_weight: f64) -> Result<Losses<B>> {
        self.loss_with(
            tokens,
            LossOptions {
                ego_weight,
                prior_drop: 0.0,
                ordinal_sigma: 0.0,
                kernels: Kernels::DEFAULT,
            },
        )
    }

    /// [`Backbone::loss`] with every option: with `prior_drop` > 0, each predicted frame's OAR input
    /// goes without its TAR prior (zeros, as in initial-scene generation) with that probability, drawn on
    /// the device from the backend's seed. The TAR's own loss always sees its output.
    pub fn loss_with(&self, tokens: Tensor<B, 3, Int>, opts: LossOptions) -> Result<Losses<B>> {
        self.loss_marked(tokens, opts, None)
    }

    /// [`Backbone::loss_with`] with the blocks' inputs marked as `ready`'s points
    /// ([`Backbone::ready_groups`] says which parameters each completes), so that data parallelism can
    /// reduce a block's gradients while the backward pass goes on.
    pub fn loss_marked(
        &self,
        tokens: Tensor<B, 3, Int>,
        opts: LossOptions,
        ready: Option<&ReadyPoints>,
    ) -> Result<Losses<B>> {
        if let Some(problem) = opts.problem() {
            return Err(BackboneError::Input(problem));
        }
        let spec = self.spec();
        let ordinal: Vec<usize> = spec.segments.iter().map(|s| s.ordinal).collect();
        let sigma = opts.ordinal_sigma;
        let k = &opts.kernels;
        let f = self.teacher_forced(tokens, opts.prior_drop, k, ready)?;
        let mut parts = Vec::new();
        let mut mean = |name: &str, sums: Vec<(Tensor<B, 1>, usize)>| {
            let count: usize = sums.iter().map(|(_, c)| c).sum();
            let mut total: Option<Tensor<B, 1>> = None;
            for ((sum, c), seg) in sums.into_iter().zip(&spec.segments) {
                parts.push((format!("{name}/{}", seg.label), sum.clone().div_scalar(c as f64)));
                total = Some(match total {
                    Some(t) => t + sum,
                    None => sum,
                });
            }
            let total = total.map(|t| t.div_scalar(count.max(1) as f64));
            if let Some(t) = &total {
                parts.push((name.to_string(), t.clone()));
            }
            total
        };
        let oar = mean(
            "oar",
            self.oar_heads
                .cross_entropy(f.o, f.target.clone(), &ordinal, sigma, k),
        );
        let tar = mean(
            "tar",
            self.tar_heads.cross_entropy(f.h, f.target, &ordinal, sigma, k),
        );
        let mut total = match (oar, tar) {
            (Some(o), Some(t)) => o + t,
            _ => return Err(BackboneError::Spec("no segments".into())),
        };
        if let (Some(logits), Some(ids)) = (self.ego_with(f.e, false, k), f.next_action) {
            let [b, t, q, v] = logits.dims();
            let bins = spec.action.as_ref().map_or(0, |a| ordinal[a.segment]);
            let ego = umgen_ops::xent::sum(
                logits.reshape([b * t * q, v]),
                ids.reshape([b * t * q, 1]),
                bins,
                sigma,
                k,
            )
            .div_scalar((b * t * q) as f64);
            parts.push(("ego".into(), ego.clone()));
            total = total + ego.mul_scalar(opts.ego_weight);
        }
        Ok(Losses { total, parts })
    }
}
