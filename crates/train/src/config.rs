//! Training settings (`[train]` in configs).

use crate::error::{Result, TrainError};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use umgen_backbone::LossOptions;
use umgen_ops::adamw::AdamWChoice;
use umgen_ops::flash::AttentionKernel;
use umgen_ops::gelu::GeluKernel;
use umgen_ops::kernel_stream::{KernelStream, LaunchThread};
use umgen_ops::matmul::MatmulKernel;
use umgen_ops::norm::NormKernel;
use umgen_ops::xent::XentKernel;
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
    /// Dataset to tokenize when the token cache is missing.
    pub data: Option<PathBuf>,
    /// Split to train on.
    pub split: String,
    /// Size of a gradient all-reduce bucket in MiB (data-parallel runs).
    pub bucket_mib: f64,
    /// Kernel of the linear layers' products when training on CUDA: `cublas` (the default; cuBLAS, falling
    /// back to `named` where it is missing), `named` (cubek's `specialized_tma_mma`,
    /// `umgen_ops::matmul`) or `burn` (burn's default kernel).
    pub matmul: MatmulKernel,
    /// MiB one query block's attention scores may take in the tiled attention (`attention::set_block_bytes`):
    /// smaller blocks skip more of a causal matrix's hidden half and launch more, smaller kernels.
    pub attention_block_mib: usize,
    /// Kernels of the training attention on CUDA: `fused` (one cubecl kernel per pass,
    /// `umgen_ops::flash`), `flash2` (FlashAttention-2 in CUDA C through NVRTC, head sizes 32 and 64;
    /// others run `fused`) or `tiled` (the tiled passes in burn tensor operations, in blocks of
    /// `attention_block_mib`).
    pub attention: AttentionKernel,
    /// Keys (or queries) per step of the fused attention kernels' loop, 16, 32 or 64
    /// (`umgen_ops::flash::set_step`): shorter steps take less shared memory per cube, so more cubes
    /// share an SM, for more loop steps and synchronisations.
    pub attention_step: usize,
    /// Recompute each self-attention layer's activations in the backward pass instead of keeping them
    /// (activation checkpointing, `umgen_ops::recompute`): the step keeps one activation per layer
    /// instead of about twenty, for one more forward pass of those layers.
    pub recompute: bool,
    /// What computes the layer norms when training on CUDA: `fused` (one CUDA C kernel per pass,
    /// `umgen_ops::norm`) or `burn` (burn's decomposition). The CPU runs the decomposition.
    pub norm: NormKernel,
    /// What computes the MLPs' bias + GELU when training: `fused` (one operation per pass writing the
    /// activation in the next product's format, on CUDA one CUDA C kernel, `umgen_ops::gelu`) or
    /// `burn` (burn's bias add and GELU in f32).
    pub gelu: GeluKernel,
    /// What computes the cross-entropy's passes over the logits when training on CUDA: `fused` (one CUDA
    /// C kernel per pass, `umgen_ops::xent`) or `burn` (burn's operations). The CPU runs burn's.
    pub xent: XentKernel,
    /// Where the CUDA C kernels (attention, layer norm, attention over time, cross-entropy) run: `cubecl`
    /// (on cubecl's own stream, launched as cubecl kernels) or `side` (a side stream per kernel family,
    /// ordered with cubecl's through device flags), `umgen_ops::kernel_stream`.
    pub kernel_stream: KernelStream,
    /// What steps AdamW when training on CUDA: `fused` (one CUDA C kernel over all parameter tensors, the
    /// clipping factor applied as it reads the gradients, `umgen_ops::adamw`) or `burn` (burn's AdamW,
    /// tensor by tensor). The CPU runs burn's.
    pub adamw: AdamWChoice,
    /// Which thread launches the custom operations' kernels and cuBLAS products on CUDA: `device`
    /// (cubecl's device thread, one blocking call per operation) or `caller` (the training thread, one
    /// blocking call to cubecl's device thread per device pointer), `umgen_ops::kernel_stream`.
    pub launch_thread: LaunchThread,
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
            bucket_mib: 25.0,
            matmul: MatmulKernel::default(),
            attention_block_mib: umgen_ops::tiled::BLOCK_BYTES >> 20,
            attention: AttentionKernel::default(),
            attention_step: umgen_ops::flash::DEFAULT_STEP,
            recompute: false,
            norm: NormKernel::default(),
            gelu: GeluKernel::default(),
            xent: XentKernel::default(),
            kernel_stream: KernelStream::default(),
            adamw: AdamWChoice::default(),
            launch_thread: LaunchThread::default(),
            nonfinite: NonFinite::default(),
            max_skipped_steps: 10,
        }
    }
}

impl TrainConfig {
    /// Applies the kernel and memory settings (`matmul`, `attention`, `attention_block_mib`,
    /// `attention_step`, `recompute`, `norm`, `gelu`, `xent`, `kernel_stream`, `adamw`, `launch_thread`) to this
    /// process, before any product runs.
    pub fn select_kernels(&self) -> Result<()> {
        if self.attention_block_mib == 0 {
            return Err(TrainError::Setup(
                "train.attention_block_mib = 0: a query block needs at least 1 MiB of scores".into(),
            ));
        }
        umgen_ops::flash::set_step(Some(self.attention_step))
            .map_err(|e| TrainError::Setup(format!("train.attention_step = {}: {e}", self.attention_step)))?;
        umgen_ops::matmul::select(self.matmul);
        umgen_ops::flash::select(self.attention);
        umgen_ops::tiled::set_block_bytes(Some(self.attention_block_mib << 20));
        umgen_ops::recompute::set_enabled(self.recompute);
        umgen_ops::norm::select(self.norm);
        umgen_ops::gelu::select(self.gelu);
        umgen_ops::xent::select(self.xent);
        umgen_ops::kernel_stream::select(self.kernel_stream);
        umgen_ops::adamw::select(self.adamw);
        umgen_ops::kernel_stream::select_thread(self.launch_thread);
        Ok(())
    }

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
        if self.attention_block_mib == 0 {
            return Some(("attention_block_mib", "0 must be 1 or more".into()));
        }
        if let Err(e) = umgen_ops::flash::check_step(self.attention_step) {
            return Some(("attention_step", e));
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

    /// The options of the training loss (`ego_loss_weight`, `prior_drop`, `ordinal_sigma`), checked: an
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
                // Same products on another kernel or in other blocks: rounding differs, the run does not.
                "matmul",
                "attention_block_mib",
                "attention",
                "attention_step",
                // Recomputed layers and the layer-norm and cross-entropy kernels give the same gradients to
                // rounding; the bias + GELU kernels the same activations to rounding, and GELU's exact
                // derivative where burn's uses the tanh approximation's.
                "recompute",
                "norm",
                "gelu",
                "xent",
                // The same kernels on another stream.
                "kernel_stream",
                // The same AdamW to rounding, with the same record.
                "adamw",
                // The same launches from another thread.
                "launch_thread",
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

#[cfg(test)]
#[path = "config_tests.rs"]
mod tests;
