//! Training settings (`[train]` in configs).

use crate::error::{Result, TrainError};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use umgen_backbone::LossOptions;
use umgen_ops::Kernels;
use umgen_optim::{AdamWSettings, adam_epsilon};

/// How the backbone is trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Run directory: checkpoints, TensorBoard, `metrics.jsonl`.
    pub out_dir: PathBuf,
    /// Optimisation steps.
    pub steps: u64,
    /// Windows per micro-batch, per process: the global batch is `batch_size × grad_accum × world size`.
    pub batch_size: usize,
    /// Micro-batches per step (their gradients are averaged).
    pub grad_accum: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Linear warm-up steps.
    pub warmup: u64,
    /// Final learning rate as a fraction of the peak (cosine decay).
    pub min_lr_ratio: f64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// AdamW β1.
    pub beta1: f64,
    /// AdamW β2.
    pub beta2: f64,
    /// AdamW ε, added to √v. Far above the gradients' size (e.g. 1) it makes AdamW a momentum SGD whose
    /// update is linear in the gradient, which is how data-parallel equivalence is measured (docs/training.md).
    pub eps: f64,
    /// Global gradient-norm clip (0 = none).
    pub grad_clip: f64,
    /// History frames T (windows hold T + 1 frames).
    pub frames: usize,
    /// Sampling gap between window frames, in dataset frames.
    pub gap: usize,
    /// Seed of initialisation, data order and dropout.
    pub seed: u64,
    /// Weight of the ego-action cross-entropy.
    pub ego_loss_weight: f64,
    /// Probability that a predicted frame's OAR trains without its TAR prior, as
    /// `umgen generate --from-scratch` runs it; a model trained with 0 has never seen that and makes
    /// poor initial scenes (the authors' `mask_temporal_pro`).
    pub prior_drop: f64,
    /// Spread, in bins, of the targets of ordered value bins (the agents' values and the ego action):
    /// their cross-entropy is taken against a Gaussian over the neighbouring bins, so a near miss scores
    /// better than a far one; 0 scores the target bin alone. Their logged losses are then KL(q ‖ p).
    pub ordinal_sigma: f64,
    /// Steps between logged metrics.
    pub log_every: u64,
    /// Steps between checkpoints.
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    pub keep_checkpoints: usize,
    /// Token cache directory (made by `umgen tokenize`, or by `umgen train` from `data`).
    pub tokens: PathBuf,
    /// Dataset to tokenize when the token cache is missing. An empty path is none: `--set train.data=""`
    /// trains from the token cache alone where the config names a dataset this machine lacks.
    #[serde(deserialize_with = "path_or_none")]
    pub data: Option<PathBuf>,
    /// Split to train on.
    pub split: String,
    /// Steps between validation passes (0 = none): the losses of `val_windows` windows of `val_split`,
    /// without dropout or `prior_drop`, logged as `val/loss`, `val/oar/agent`, … next to the training
    /// losses, and after the last step. On a split of networks the run never trains on, they show when
    /// what it learns stops carrying over.
    pub val_every: u64,
    /// Split the validation windows come from (tokenized into `tokens` beside the training split).
    pub val_split: String,
    /// Windows scored in each validation pass, spread evenly over the split.
    pub val_windows: usize,
    /// Size of a gradient all-reduce bucket in MiB (data-parallel runs).
    pub bucket_mib: f64,
    /// Share AdamW's state out among the ranks of a data-parallel run (ZeRO stage 1): each rank keeps the
    /// moments of about 1/world of the parameters, updates those and sends them to the others. Steps and
    /// checkpoints are the same as without it; a run may resume with it on or off.
    pub shard_optimizer: bool,
    /// The kernel choices (`[train.kernels]`, [`Kernels`]): which kernels run the products, the attention,
    /// the norms, GELU, the cross-entropy and AdamW on CUDA, on which stream and from which thread, the
    /// tiled attention's block size, and activation checkpointing. They change speed and memory, not
    /// results (beyond rounding), so a run may resume under other choices.
    pub kernels: Kernels,
    /// What a step whose loss or gradient norm is not finite does: `skip` (the default: the step leaves
    /// the weights and AdamW's moments as they were, and the run stops after `max_skipped_steps` such
    /// steps in a row) or `stop` (the run stops with an error naming the step). Either way no checkpoint
    /// is written from a skipped step.
    pub nonfinite: NonFinite,
    /// Skipped steps in a row after which a run with `nonfinite = "skip"` stops with an error.
    pub max_skipped_steps: u64,
}

/// What a training step with a non-finite loss or gradient norm does (`train.nonfinite`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NonFinite {
    /// Leave the weights and optimizer state as they were and go on, up to `train.max_skipped_steps` in a
    /// row.
    #[default]
    Skip,
    /// Stop the run with an error at the first such step.
    Stop,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            out_dir: "runs/train".into(),
            steps: 1000,
            batch_size: 8,
            grad_accum: 1,
            lr: 1e-4,
            warmup: 100,
            min_lr_ratio: 0.1,
            weight_decay: 0.01,
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            grad_clip: 1.0,
            frames: 20,
            gap: 1,
            seed: 0,
            ego_loss_weight: 1.0,
            prior_drop: 0.0,
            ordinal_sigma: 0.0,
            log_every: 10,
            checkpoint_every: 500,
            keep_checkpoints: 3,
            tokens: "runs/tokens".into(),
            data: None,
            split: "train".into(),
            val_every: 0,
            val_split: "test".into(),
            val_windows: 64,
            bucket_mib: 25.0,
            shard_optimizer: false,
            kernels: Kernels::default(),
            nonfinite: NonFinite::default(),
            max_skipped_steps: 10,
        }
    }
}

impl TrainConfig {
    /// The first setting that no run can use, as (key under `[train]`, what is wrong with its value);
    /// `None` when every one is usable. `UmgenConfig::load` refuses such a config before anything runs,
    /// naming the key and where it was set.
    pub fn problem(&self) -> Option<(&'static str, String)> {
        let at_least_one: [(&'static str, u64); 8] = [
            ("steps", self.steps),
            ("batch_size", self.batch_size as u64),
            ("grad_accum", self.grad_accum as u64),
            ("frames", self.frames as u64),
            ("gap", self.gap as u64),
            ("log_every", self.log_every),
            ("checkpoint_every", self.checkpoint_every),
            ("keep_checkpoints", self.keep_checkpoints as u64),
        ];
        if let Some((key, v)) = at_least_one.into_iter().find(|(_, v)| *v == 0) {
            return Some((key, format!("{v} must be 1 or more")));
        }
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let non_negative = |x: f64| x.is_finite() && x >= 0.0;
        let fraction = |x: f64| (0.0..1.0).contains(&x);
        let numbers: [(&'static str, f64, bool, &str); 7] = [
            ("lr", self.lr, positive(self.lr), "a positive number"),
            (
                "min_lr_ratio",
                self.min_lr_ratio,
                (0.0..=1.0).contains(&self.min_lr_ratio),
                "a fraction of the peak, 0 to 1",
            ),
            (
                "weight_decay",
                self.weight_decay,
                non_negative(self.weight_decay),
                "0 or a positive number",
            ),
            (
                "beta1",
                self.beta1,
                fraction(self.beta1),
                "at least 0 and below 1",
            ),
            (
                "beta2",
                self.beta2,
                fraction(self.beta2),
                "at least 0 and below 1",
            ),
            (
                "grad_clip",
                self.grad_clip,
                non_negative(self.grad_clip),
                "0 (no clipping) or a positive norm",
            ),
            (
                "ego_loss_weight",
                self.ego_loss_weight,
                non_negative(self.ego_loss_weight),
                "0 or a positive weight",
            ),
        ];
        if let Some((key, v, _, want)) = numbers.into_iter().find(|(_, _, ok, _)| !ok) {
            return Some((key, format!("{v} must be {want}")));
        }
        if !positive(self.bucket_mib) {
            return Some((
                "bucket_mib",
                format!("{} must be a positive size", self.bucket_mib),
            ));
        }
        if adam_epsilon(self.eps).is_none() {
            return Some((
                "eps",
                format!("{} must be a positive number that f32 holds", self.eps),
            ));
        }
        if let Some((key, why)) = self.kernels.problem() {
            // The key under `[train]` (`Kernels::problem` names it under `[train.kernels]`).
            let key = match key {
                "attention_step" => "kernels.attention_step",
                "attention_block_mib" => "kernels.attention_block_mib",
                "flash2_warps" => "kernels.flash2_warps",
                "attention_backward" => "kernels.attention_backward",
                _ => "kernels",
            };
            return Some((key, why));
        }
        if self.val_every > 0 && self.val_windows == 0 {
            return Some((
                "val_windows",
                "0 must be 1 or more while train.val_every is set".into(),
            ));
        }
        if self.max_skipped_steps == 0 {
            return Some((
                "max_skipped_steps",
                "0 must be 1 or more (train.nonfinite = \"stop\" stops at the first)".into(),
            ));
        }
        if let Some(p) = self.loss_options_unchecked().problem() {
            let key = if p.starts_with("prior_drop") {
                "prior_drop"
            } else {
                "ordinal_sigma"
            };
            let value = p
                .split_once(" = ")
                .map_or(p.clone(), |(_, rest)| rest.to_string());
            return Some((key, value));
        }
        None
    }

    /// AdamW's settings (`beta1`, `beta2`, `eps`, `weight_decay`) as the optimizer takes them, checked: an
    /// ε that f32 cannot hold is an error naming `train.eps`. `umgen train` and `umgen bench train` step
    /// with these.
    pub fn adamw_settings(&self) -> Result<AdamWSettings> {
        let Some(epsilon) = adam_epsilon(self.eps) else {
            return Err(TrainError::Setup(format!(
                "train.eps = {} must be a positive number that f32 holds",
                self.eps
            )));
        };
        Ok(AdamWSettings {
            beta_1: self.beta1 as f32,
            beta_2: self.beta2 as f32,
            epsilon,
            weight_decay: self.weight_decay as f32,
        })
    }

    /// The options of the training loss (`ego_loss_weight`, `prior_drop`, `ordinal_sigma`, `kernels`), checked: an
    /// error names the key and its value. `umgen train` and `umgen bench train` take the loss this way.
    pub fn loss_options(&self) -> Result<LossOptions> {
        let options = self.loss_options_unchecked();
        match options.problem() {
            Some(problem) => Err(TrainError::Setup(format!("train.{problem}"))),
            None => Ok(options),
        }
    }

    fn loss_options_unchecked(&self) -> LossOptions {
        LossOptions {
            ego_weight: self.ego_loss_weight,
            prior_drop: self.prior_drop,
            ordinal_sigma: self.ordinal_sigma,
            kernels: self.kernels,
        }
    }

    /// The settings a resumed run must share with the run it continues (everything that changes the
    /// trajectory; `steps`, logging and checkpoint cadence may change).
    pub fn identity(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).unwrap_or(serde_json::Value::Null);
        if let Some(o) = v.as_object_mut() {
            for k in [
                "out_dir",
                "steps",
                "log_every",
                "checkpoint_every",
                "keep_checkpoints",
                "tokens",
                "data",
                "bucket_mib",
                // Validation reads the weights; it changes nothing a step does.
                "val_every",
                "val_split",
                "val_windows",
                // Every parameter steps to the same bits, sharded or not (`umgen_dist::Shards`).
                "shard_optimizer",
                // Same products on other kernels, streams or threads, in other blocks, recomputed or kept:
                // rounding differs, the run does not (each choice in `Kernels`' docs).
                "kernels",
                // What happens to a step that breaks the run, not how the run trains.
                "nonfinite",
                "max_skipped_steps",
            ] {
                o.remove(k);
            }
            // Runs from before ε was a setting used the default: their checkpoints stay resumable.
            if self.eps == Self::default().eps {
                o.remove("eps");
            }
            // Likewise runs from before the prior drop, which trained without it.
            if self.prior_drop == 0.0 {
                o.remove("prior_drop");
            }
            // And from before ordinal smoothing.
            if self.ordinal_sigma == 0.0 {
                o.remove("ordinal_sigma");
            }
        }
        v
    }
}

/// An optional path where an empty one means none.
fn path_or_none<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Option<PathBuf>, D::Error> {
    let p = Option::<PathBuf>::deserialize(d)?;
    Ok(p.filter(|p| !p.as_os_str().is_empty()))
}

#[cfg(test)]
#[path = "config_tests.rs"]
mod tests;
