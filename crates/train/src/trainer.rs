//! The training loop.

use crate::error::{Result, TrainError};
use crate::guard::Guard;
use crate::losses::{averaged_parts, step_losses};
use crate::run::{RunSpec, claim_run_dir, describe_difference};
use crate::sampler::Sampler;
use crate::validate::{Validation, load_batch};
use burn::optim::{GradientsAccumulator, GradientsParams};
use burn::tensor::backend::AutodiffBackend;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;
use umgen_backbone::Backbone;
use umgen_checkpoint::CheckpointDir;
use umgen_checkpoint::burn_io::{
    first_non_finite, optimizer_from_bytes, optimizer_to_bytes, stable_param_ids, weights_from_bytes,
    weights_to_bytes,
};
use umgen_data::TokenSet;
use umgen_dist::{Overlap, ProcessGroup, Shards, broadcast_module, rank0_decides, same_on_all_ranks};
use umgen_metrics::MetricLog;
use umgen_optim::{FusedAdamW, Schedule};

/// Checkpoint kind of backbone runs.
pub const KIND: &str = "backbone";

/// One step, reported to the caller.
#[derive(Debug, Clone)]
pub struct StepReport {
    /// Steps done.
    pub step: u64,
    /// Steps in all.
    pub steps: u64,
    /// Seconds per step: on logging steps the mean since the previous logging step (the device's work
    /// included, since logging reads the losses); on other steps the host's time for this step, which does
    /// not wait for the device.
    pub seconds: f64,
    /// Tokens per second (B · T · N · accum / `seconds`).
    pub tokens_per_s: f64,
    /// Logged scalars on logging steps: `loss`, per-modality losses, `lr`, `grad_norm`, `tokens_per_s`.
    pub values: Option<Vec<(String, f64)>>,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Step reached.
    pub step: u64,
    /// First logged loss of this process (`None` if nothing was logged).
    pub first_loss: Option<f64>,
    /// Last logged loss.
    pub last_loss: Option<f64>,
    /// Newest checkpoint.
    pub checkpoint: Option<PathBuf>,
}

fn mix(seed: u64, step: u64) -> u64 {
    let mut z = seed
        ^ step
            .wrapping_add(0x9e37_79b9_7f4a_7c15)
            .wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 30)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Trains the backbone on windows of `tokens` into `train.out_dir`. With `resume`, continues from the
/// newest good checkpoint (which must belong to the same run); without it, refuses a directory that
/// already holds checkpoints. Every step is reseeded from (seed, step) and the data order is a function of
/// (seed, epoch), so a resumed run repeats the uninterrupted one. `on_step` may stop the run
/// (`ControlFlow::Break`) after a checkpoint; with several ranks, rank 0's answer on logging steps
/// counts (the others are ignored), so every rank stops at the same step.
///
/// Data parallel over `group`: every rank starts from rank 0's parameters, reads its own slice of each
/// step's samples, and averages gradients (in buckets of `bucket_mib`) once per step, during the last
/// accumulation micro-step's backward pass, each block's bucket as soon as that pass has completed it
/// ([`Overlap`]); clipping and AdamW then run identically on every rank, or, with
/// `train.shard_optimizer`, each rank updates its share of the parameters and sends them to the others
/// ([`Shards`]; checkpoints hold the whole state either way). Only rank 0 writes metrics and checkpoints.
/// Resuming with another world size restores weights and optimizer state, but the global batch and the
/// data order from there on differ from the original run (a warning says so).
pub fn train<B: AutodiffBackend>(
    run: &RunSpec,
    tokens: &TokenSet,
    device: &B::Device,
    resume: bool,
    group: &mut dyn ProcessGroup<B::InnerBackend>,
    mut on_step: impl FnMut(&StepReport) -> ControlFlow<()>,
) -> Result<Summary> {
    let tc = &run.train;
    let (rank, world) = (group.rank(), group.world_size());
    let lead = rank == 0;
    let bucket = (tc.bucket_mib * 1048576.0).max(4.0) as usize;
    let out = &tc.out_dir;
    let f = tc.frames + 1;
    let windows = tokens.windows(f, tc.gap, Some(&tc.split));
    if windows.is_empty() || tc.batch_size == 0 || tc.grad_accum == 0 || tc.frames == 0 {
        return Err(TrainError::Setup(format!(
            "no training windows of {f} frames at gap {} in split `{}` (or a zero batch size / accumulation / frames)",
            tc.gap, tc.split
        )));
    }
    let step = tokens.index().frame_interval * tc.gap as f64;
    if let Some(k) = &run.spec.track
        && !k.steps_by(step)
    {
        return Err(TrainError::Setup(format!(
            "backbone.step_s = {} s, but the windows step {step} s (frames {} s apart, train.gap {}): \
             the tracked slots would be moved by the wrong time; set backbone.step_s = {step}",
            k.step_s,
            tokens.index().frame_interval,
            tc.gap
        )));
    }
    let settings = tc.adamw_settings()?;
    let loss_options = tc.loss_options()?;
    if f > run.backbone.max_frames {
        return Err(TrainError::Setup(format!(
            "windows of {f} frames exceed backbone.max_frames = {}",
            run.backbone.max_frames
        )));
    }
    B::seed(device, tc.seed);
    let mut model = stable_param_ids(Backbone::<B>::new(&run.backbone, &run.spec, device)?);
    let mut optim = FusedAdamW::<_, B>::new(settings)
        .with_kernels(umgen_ops::adamw::kernels::<B::InnerBackend>(&tc.kernels));
    let shards = (tc.shard_optimizer && world > 1).then(|| Shards::plan::<B, _>(&model, rank, world));
    if tc.shard_optimizer && world == 1 {
        tracing::info!(
            "train.shard_optimizer: one rank has nothing to share, the optimizer state stays whole"
        );
    }
    optim.set_owned(shards.as_ref().map(Shards::owned));
    if let (Some(s), true) = (&shards, lead) {
        let total: usize = s.loads().iter().sum();
        let millions = |n: &usize| format!("{:.1} M", *n as f64 / 1e6);
        tracing::info!(
            "optimizer state sharded over {world} ranks: {} of {:.1} M parameters a rank",
            s.loads().iter().map(millions).collect::<Vec<_>>().join(", "),
            total as f64 / 1e6,
        );
    }
    let ckpts = CheckpointDir::new(out.join("checkpoints"), tc.keep_checkpoints);
    let mut step = 0u64;
    let mut last_ckpt = None;
    if resume {
        // No checkpoint at all starts the run (a scheduler may pass --resume to every attempt); checkpoints
        // of which none verifies are an error that names each, and nothing is touched.
        let latest = ckpts.load_latest()?;
        if latest.is_none() && lead {
            tracing::info!(
                "--resume: no checkpoint in {} yet, starting at step 1",
                ckpts.root().display()
            );
        }
        if let Some(l) = latest {
            let saved = &l.manifest.meta["identity"];
            if l.manifest.kind != KIND || saved != &run.identity() {
                return Err(TrainError::Checkpoint(
                    umgen_checkpoint::CheckpointError::Mismatch {
                        path: l.dir.clone(),
                        reason: describe_difference(saved, &run.identity()),
                    },
                ));
            }
            model = weights_from_bytes(
                model,
                l.file("model.safetensors")?.to_vec(),
                "backbone checkpoint",
            )?;
            let bytes = l.file("optimizer.bin")?;
            optim = match &shards {
                Some(s) => crate::shard::load_share(optim, bytes, device, s)?,
                None => optimizer_from_bytes::<B, _, _>(optim, bytes.to_vec(), device)?,
            };
            step = l.manifest.step;
            let saved_world = l.manifest.meta["world_size"].as_u64().unwrap_or(1);
            if saved_world != world as u64 && lead {
                tracing::warn!(
                    "{} was written by {saved_world} rank(s), this run has {world}: weights and optimizer state continue, but the global batch is now {} windows and the data order differs from an uninterrupted run",
                    l.dir.display(),
                    tc.batch_size * tc.grad_accum * world
                );
            }
            if lead {
                tracing::info!("resuming from {} (step {step})", l.dir.display());
            }
            last_ckpt = Some(l.dir);
        }
    } else if !ckpts.list()?.is_empty() {
        return Err(TrainError::RunDir { path: out.clone(), message: "holds checkpoints of an earlier run: pass --resume to continue it, or choose another train.out_dir".into() });
    }
    // Rank 0's parameters everywhere (also after a resume: all ranks loaded the same checkpoint, but a
    // broadcast makes that a guarantee rather than an assumption about the file system).
    model = broadcast_module(model, group, bucket)?;
    same_on_all_ranks(
        group,
        step,
        "the step this run starts from (ranks need train.out_dir on a shared file system)",
        device,
    )?;
    // Every rank must take part in a sharded step's exchanges, or none.
    same_on_all_ranks(
        group,
        u64::from(tc.shard_optimizer),
        "train.shard_optimizer",
        device,
    )?;
    if lead {
        claim_run_dir(run, &ckpts, step)?;
    }
    let mut log = if lead {
        Some(MetricLog::open(out).map_err(|error| TrainError::Metrics {
            path: out.clone(),
            error,
        })?)
    } else {
        None
    };
    let schedule = Schedule {
        peak: tc.lr,
        warmup: tc.warmup,
        total: tc.steps,
        floor: tc.min_lr_ratio,
    };
    // Rank 0 validates (the others go on to the next step's exchanges and wait there).
    let validation = if lead {
        Validation::new(tc, tokens, f)?
    } else {
        None
    };
    let mut sampler = Sampler::new(windows.len(), tc.seed);
    let n = run.spec.n;
    let tokens_per_step = (tc.batch_size * tc.frames * n * tc.grad_accum * world) as f64;
    let rank_salt = (rank as u64).wrapping_mul(0xd1b5_4a32_d192_ed03);
    let (mut first_loss, mut last_loss) = (None, None);
    let (mut interval, mut interval_from) = (Instant::now(), step);
    let mut guard = Guard::new(tc.nonfinite, tc.max_skipped_steps, world, step, device);
    while step < tc.steps {
        let t0 = Instant::now();
        // Dropout differs between ranks (they see different samples) and is a function of (seed, step, rank).
        B::seed(device, mix(tc.seed, step) ^ rank_salt);
        let mut acc = GradientsAccumulator::new();
        let mut parts = Vec::new();
        let mut reduced = None;
        for micro in 0..tc.grad_accum {
            let picks = sampler.batch(step, micro, tc.grad_accum, tc.batch_size, rank, world);
            let batch = load_batch::<B>(tokens, &windows, &picks, f, tc.gap, n, device)?;
            let scale = tc.grad_accum as f64;
            let losses = if world > 1 && micro + 1 == tc.grad_accum {
                // The last micro-step's backward pass starts each block's all-reduce as it completes
                // the block's gradients (the earlier micro-steps' added); the others communicate nothing.
                let overlap = Overlap::<B>::new(&model, &model.ready_groups(), acc.grads(), &*group, bucket);
                let losses = model.loss_marked(batch, loss_options, Some(&overlap.points()))?;
                reduced = Some(overlap.finish(losses.total.clone().div_scalar(scale).backward(), group)?);
                losses
            } else {
                let losses = model.loss_with(batch, loss_options)?;
                let grads =
                    GradientsParams::from_grads(losses.total.clone().div_scalar(scale).backward(), &model);
                acc.accumulate(&model, grads);
                losses
            };
            parts.push(losses);
        }
        let grads = match reduced {
            Some(g) => g,
            None => acc.grads(),
        };
        let lr = schedule.lr(step);
        let losses = step_losses(&parts);
        let guarded = guard.values(losses.clone().slice(0..1));
        let stepped = optim.step_clipped(lr, model, grads, tc.grad_clip, guarded);
        model = match &shards {
            Some(s) => s.gather::<B, _>(stepped.module, group)?,
            None => stepped.module,
        };
        let grad_norm = stepped.norm;
        guard.observe(stepped.skipped, losses, grad_norm.clone(), stepped.parts);
        step += 1;
        let mut seconds = t0.elapsed().as_secs_f64();
        let logging = step.is_multiple_of(tc.log_every.max(1)) || step == tc.steps || step == 1;
        let values = if logging {
            // Reading the losses waits for the device; nothing else in a step does (clipping stays on the
            // device), so time is only meaningful averaged over the steps since the previous log.
            let (mut v, skips) = averaged_parts(&parts, group, lr, grad_norm, guard.pending())?;
            seconds = interval.elapsed().as_secs_f64() / (step - interval_from).max(1) as f64;
            (interval, interval_from) = (Instant::now(), step);
            v.push(("tokens_per_s".into(), tokens_per_step / seconds));
            write_metrics(log.as_mut(), out, step, &v)?;
            let names: Vec<String> = v
                .iter()
                .take_while(|(k, _)| k != "lr")
                .map(|(k, _)| k.clone())
                .collect();
            let report = guard.settle(&skips, step, &names, |p| optim.largest_gradient(p))?;
            if let (Some(r), true) = (report, lead) {
                tracing::warn!(
                    "{} step(s) skipped since the last log ({} in a row now; the run stops at train.max_skipped_steps = {}), the first at step {}: {}",
                    r.skipped,
                    r.streak,
                    tc.max_skipped_steps,
                    r.step,
                    r.what
                );
            }
            first_loss = first_loss.or(Some(v[0].1));
            last_loss = Some(v[0].1);
            Some(v)
        } else {
            None
        };
        let stop = on_step(&StepReport {
            step,
            steps: tc.steps,
            seconds,
            tokens_per_s: tokens_per_step / seconds,
            values,
        })
        .is_break();
        // Exchanged only where the loss averaging has already made the ranks wait for each other, so
        // other steps keep the host ahead of the device.
        let stop = match world {
            1 => stop,
            _ => logging && rank0_decides(group, stop, device)?,
        };
        let due = stop || step.is_multiple_of(tc.checkpoint_every.max(1)) || step == tc.steps;
        let skipping = due && lead && guard.streak_now() > 0.0;
        if skipping {
            tracing::warn!(
                "no checkpoint at step {step}: the step was skipped (its loss or gradient norm is not finite)"
            );
        }
        // A sharded optimizer's state comes to rank 0 from every rank.
        let gathered = match (&shards, due) {
            (Some(s), true) => crate::shard::gathered_bytes(&optim, &model, s, group)?,
            _ => None,
        };
        if due && lead && !skipping {
            let meta =
                serde_json::json!({"identity": run.identity(), "config": run.config, "world_size": world});
            let w = weights_to_bytes(&model)?;
            if let Some(name) = first_non_finite(&w)? {
                return Err(TrainError::NonFinite {
                    step,
                    message: format!("the weights of `{name}` hold values that are not finite"),
                });
            }
            let o = match gathered {
                Some(o) => o,
                None => optimizer_to_bytes::<B, _, _>(&optim)?,
            };
            last_ckpt = Some(ckpts.save(
                KIND,
                step,
                meta,
                &[("model.safetensors", &w), ("optimizer.bin", &o)],
            )?);
        }
        if let Some(v) = validation.as_ref().filter(|v| stop || v.due(step, tc.steps)) {
            let values = v.losses(&model, tokens, loss_options, device)?;
            let shown: Vec<String> = values.iter().map(|(k, x)| format!("{k} {x:.4}")).collect();
            tracing::info!(
                "step {step}: {} ({} windows of split `{}`)",
                shown.join(", "),
                v.len(),
                tc.val_split
            );
            write_metrics(log.as_mut(), out, step, &values)?;
        }
        if stop {
            if lead {
                tracing::info!("stopped at step {step} of {}", tc.steps);
            }
            break;
        }
    }
    // Nobody leaves before the last checkpoint is written and every rank is done.
    group.barrier()?;
    group.finish();
    Ok(Summary {
        step,
        first_loss,
        last_loss,
        checkpoint: last_ckpt,
    })
}

/// Logs `values` at `step` into the run's metrics (rank 0 holds the log) and flushes them, so that a
/// killed run keeps every line written.
fn write_metrics(log: Option<&mut MetricLog>, out: &Path, step: u64, values: &[(String, f64)]) -> Result<()> {
    let Some(log) = log else {
        return Ok(());
    };
    log.log(
        step,
        &values.iter().map(|(k, x)| (k.as_str(), *x)).collect::<Vec<_>>(),
    )
    .and_then(|()| log.flush())
    .map_err(|error| TrainError::Metrics {
        path: out.to_path_buf(),
        error,
    })
}
