//! Training a VQ tokenizer: AdamW with warm-up + cosine, global-norm clipping, EMA codebook with dead-code
//! restarts, checkpoints and TensorBoard scalars; resumable from the last good checkpoint; alone or
//! data-parallel over a process group.

use crate::config::{VqConfig, VqTrainConfig};
use crate::error::{Result, VqError};
use crate::loss::{commitment, reconstruction_over};
use crate::metrics::count_stats;
use crate::model::VqModel;
use crate::source::{RasterSource, batch_indices, render};
use crate::tokenizer::{TokenizerInfo, VqTokenizer};
use burn::module::AutodiffModule;
use burn::optim::{AdamWConfig, GradientsParams, Optimizer};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;
use umgen_checkpoint::CheckpointDir;
use umgen_checkpoint::burn_io::{
    optimizer_from_bytes, optimizer_to_bytes, stable_param_ids, weights_from_bytes, weights_to_bytes,
};
use umgen_dist::{
    ProcessGroup, Single, all_reduce_grads, broadcast_module, rank0_decides, same_on_all_ranks,
};
use umgen_metrics::MetricLog;
use umgen_optim::{Schedule, adam_epsilon, clip_grad_norm};

/// Checkpoint kind of tokenizer runs.
pub const KIND: &str = "vq-tokenizer";
/// Steps between checks for dead codes.
const RESTART_CHECK: u64 = 10;
/// Steps whose code histograms make the logged usage and perplexity.
const RECENT: usize = 8;
/// Gradient all-reduce buckets.
const BUCKET_BYTES: usize = 25 << 20;

/// What one training step did; `values` only on logging steps.
#[derive(Debug, Clone)]
pub struct StepReport {
    /// Steps done.
    pub step: u64,
    /// Steps in all.
    pub steps: u64,
    /// Seconds of this step.
    pub seconds: f64,
    /// Logged scalars (losses, codebook usage and perplexity, learning rate, gradient norm, throughput).
    pub values: Option<Vec<(&'static str, f64)>>,
}

/// Trains a tokenizer of `config` on rasters from `source` into `out` (checkpoints in
/// `out/checkpoints`, metrics in `out/tb` and `out/metrics.jsonl`, the result in `out/vq.json` and
/// `out/vq.safetensors`). Resumes from the newest good checkpoint when there is one. `on_step` sees every
/// step; returning `ControlFlow::Break` stops training after a checkpoint (a later call resumes there).
pub fn train<B: AutodiffBackend>(
    config: &VqConfig,
    tc: &VqTrainConfig,
    source: &dyn RasterSource,
    out: &Path,
    device: &B::Device,
    on_step: impl FnMut(&StepReport) -> ControlFlow<()>,
) -> Result<VqTokenizer<B::InnerBackend>> {
    train_on::<B>(config, tc, source, out, device, &mut Single, on_step)
}

/// [`train`] as one rank of a data-parallel job over `group`. Each rank draws its own slice of every
/// step's `batch_size × world size` rasters (rank 0's slice is what a single process would draw); all
/// ranks start from rank 0's parameters and codebook; gradients are averaged (the codebook's moving
/// averages are fed the sums of every rank's assignments), so every rank holds the same model. Dead
/// codes restart from rank 0's encoder outputs. Only rank 0 writes metrics, checkpoints and the
/// tokenizer, and only its `on_step` decides when to stop.
pub fn train_on<B: AutodiffBackend>(
    config: &VqConfig,
    tc: &VqTrainConfig,
    source: &dyn RasterSource,
    out: &Path,
    device: &B::Device,
    group: &mut dyn ProcessGroup<B::InnerBackend>,
    mut on_step: impl FnMut(&StepReport) -> ControlFlow<()>,
) -> Result<VqTokenizer<B::InnerBackend>> {
    let (rank, world) = (group.rank(), group.world_size());
    let lead = rank == 0;
    let Some(eps) = adam_epsilon(tc.eps) else {
        return Err(VqError::Config {
            key: "vq_train.eps".into(),
            message: format!("{} is not a positive number that f32 holds", tc.eps),
        });
    };
    config.validate("vq")?;
    let [c, h, w] = source.shape();
    if c != config.channels
        || !h.is_multiple_of(config.downsampling())
        || !w.is_multiple_of(config.downsampling())
        || source.is_empty()
    {
        return Err(VqError::Data(format!(
            "{} rasters of {c}×{h}×{w} do not fit a {}-channel tokenizer with {}× downsampling",
            source.len(),
            config.channels,
            config.downsampling()
        )));
    }
    B::seed(device, tc.seed);
    let mut model = stable_param_ids(VqModel::<B>::new(config, device));
    let mut optim = AdamWConfig::new()
        .with_beta_2(0.95)
        .with_epsilon(eps)
        .with_weight_decay(tc.weight_decay as f32)
        .init();
    let ckpts = CheckpointDir::new(out.join("checkpoints"), tc.keep_checkpoints);
    let k = config.codebook_size;
    let (mut step, mut last_used) = (0u64, vec![0u64; k]);
    if let Some(l) = ckpts.load_latest()? {
        let saved: VqConfig = serde_json::from_value(l.manifest.meta["config"].clone())
            .map_err(|e| mismatch(&l.dir, e.to_string()))?;
        if l.manifest.kind != KIND || &saved != config {
            return Err(mismatch(
                &l.dir,
                format!("it holds a `{}` of another configuration", l.manifest.kind),
            ));
        }
        model = weights_from_bytes(
            model,
            l.file("model.safetensors")?.to_vec(),
            "tokenizer checkpoint",
        )?;
        optim = optimizer_from_bytes::<B, _, _>(optim, l.file("optimizer.bin")?.to_vec(), device)?;
        step = l.manifest.step;
        last_used = serde_json::from_value(l.manifest.meta["last_used"].clone())
            .map_err(|e| mismatch(&l.dir, e.to_string()))?;
        let saved_world = l.manifest.meta["world_size"].as_u64().unwrap_or(1);
        if lead && saved_world != world as u64 {
            tracing::warn!(
                "{} was written by {saved_world} rank(s), this run has {world}: the model continues, but the batches from here on differ from an uninterrupted run",
                l.dir.display()
            );
        }
        if lead {
            tracing::info!(
                "resuming tokenizer training from {} (step {step})",
                l.dir.display()
            );
        }
    }
    same_on_all_ranks(
        group,
        step,
        "the step this run starts from (ranks need the run directory on a shared file system)",
        device,
    )?;
    let mut log = if lead {
        Some(MetricLog::open(out).map_err(|error| VqError::Metrics {
            path: out.into(),
            error,
        })?)
    } else {
        None
    };
    let schedule = Schedule {
        peak: tc.lr,
        warmup: tc.warmup,
        total: tc.steps,
        floor: 0.1,
    };
    let threads = if tc.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        tc.threads
    };
    let rasters = |ids: &[usize]| -> Result<Tensor<B, 4>> {
        let data = render(source, ids, threads)?;
        Ok(Tensor::from_data(
            TensorData::new(data, [ids.len(), c, h, w]),
            device,
        ))
    };
    let global = |s: u64| batch_indices(source.len(), tc.seed, s, tc.batch_size * world);
    let batch = |s: u64| rasters(&global(s)[rank * tc.batch_size..(rank + 1) * tc.batch_size]);
    if step == 0 && lead {
        // Start the codebook on encoder outputs of the first global batch (encoded a rank's batch at a
        // time), so that every code is near data and the start does not depend on the world size.
        let rows = global(0)
            .chunks(tc.batch_size.max(1))
            .map(|ids| Ok(model.encode_rows(rasters(ids)?).0.detach()))
            .collect::<Result<Vec<_>>>()?;
        let rows = Tensor::cat(rows, 0);
        let n = rows.dims()[0];
        let mut rng = StdRng::seed_from_u64(tc.seed ^ 0x5eed);
        let pick: Vec<i64> = (0..k).map(|_| rng.random_range(0..n) as i64).collect();
        let noise = Tensor::random(
            [k, config.embed_dim],
            burn::tensor::Distribution::Normal(0.0, 0.01),
            device,
        );
        let vectors = rows
            .detach()
            .select(0, Tensor::from_data(TensorData::new(pick, [k]), device))
            + noise;
        let all = Tensor::<B, 1, Int>::arange(0..k as i64, device);
        model.quantizer = model.quantizer.restart(all, vectors);
    }
    // Rank 0's parameters and codebook everywhere (also after a resume, whatever the file system).
    model = broadcast_module(model, group, BUCKET_BYTES)?;
    let mut recent: std::collections::VecDeque<Vec<f64>> = std::collections::VecDeque::new();
    while step < tc.steps {
        let t0 = Instant::now();
        let x = batch(step)?;
        let fwd = model.forward(x.clone());
        let rec = reconstruction_over(config.output, &tc.loss, fwd.recon, x, world, |sums| {
            let mean = group.all_reduce_mean(sums.inner())?;
            Ok::<_, VqError>(Tensor::from_inner(mean.mul_scalar(world as f64)))
        })?;
        let commit = commitment(fwd.quantized.z.clone(), fwd.quantized.z_q.clone());
        let loss = rec.total.clone() + commit.clone().mul_scalar(tc.loss.commitment);
        let objective = rec.objective + commit.clone().mul_scalar(tc.loss.commitment);
        let grads = GradientsParams::from_grads(objective.backward(), &model);
        let mut grads = all_reduce_grads(&model.trainable(), grads, group, BUCKET_BYTES)?;
        let grad_norm = clip_grad_norm::<B, _>(&model, &mut grads, tc.grad_clip);
        let lr = schedule.lr(step);
        model = optim.step(lr, model, grads);
        let z = fwd.quantized.z.detach();
        // Every rank's assignments feed the moving averages, summed (a mean times the world size).
        let mut stats = model
            .quantizer
            .assignment(z.clone(), fwd.quantized.indices)
            .inner();
        if world > 1 {
            stats = group.all_reduce_mean(stats)?.mul_scalar(world as f64);
        }
        let counts: Vec<f64> = stats.clone().narrow(0, 0, k).into_data().iter::<f64>().collect();
        model.quantizer = model.quantizer.ema_apply(Tensor::from_inner(stats), tc.ema_decay);
        step += 1;
        for (i, _) in counts.iter().enumerate().filter(|(_, c)| **c > 0.0) {
            last_used[i] = step;
        }
        if step.is_multiple_of(RESTART_CHECK) {
            let restarted;
            (model.quantizer, restarted) = restart_dead(model.quantizer, &last_used, step, tc, z, device);
            if restarted > 0 {
                model.quantizer = broadcast_module(model.quantizer, group, BUCKET_BYTES)?;
            }
        }
        recent.push_back(counts);
        if recent.len() > RECENT {
            recent.pop_front();
        }
        let logging = step.is_multiple_of(tc.log_every.max(1)) || step == tc.steps;
        let values = if logging {
            let mut names: Vec<&'static str> = vec!["loss/total"];
            let mut parts = vec![loss];
            for (n, t) in rec.parts {
                names.push(n);
                parts.push(t);
            }
            names.push("commitment");
            parts.push(commit);
            // The gradient norm rides along in the same transfer, last.
            parts.push(Tensor::from_inner(grad_norm));
            let mut logged = Tensor::cat(parts, 0).inner();
            if world > 1 {
                logged = group.all_reduce_mean(logged)?;
            }
            let mut got: Vec<f64> = logged.into_data().iter::<f64>().collect();
            let grad_norm = got.pop().unwrap_or(f64::NAN);
            let (usage, ppl) = count_stats(&histogram(&recent, k));
            let secs = t0.elapsed().as_secs_f64();
            let mut v: Vec<(&'static str, f64)> = names.into_iter().zip(got).collect();
            v.extend([
                ("codebook/usage", usage),
                ("codebook/perplexity", ppl),
                ("lr", lr),
                ("grad_norm", grad_norm),
                ("rasters_per_s", (tc.batch_size * world) as f64 / secs),
            ]);
            if let Some(log) = log.as_mut() {
                log.log(step, &v)
                    .and_then(|()| log.flush())
                    .map_err(|error| VqError::Metrics {
                        path: out.into(),
                        error,
                    })?;
            }
            Some(v)
        } else {
            None
        };
        let stop = on_step(&StepReport {
            step,
            steps: tc.steps,
            seconds: t0.elapsed().as_secs_f64(),
            values,
        })
        .is_break();
        let stop = rank0_decides(group, stop, device)?;
        if lead && (stop || step.is_multiple_of(tc.checkpoint_every.max(1)) || step == tc.steps) {
            let meta = serde_json::json!({"config": config, "train": tc, "last_used": last_used, "world_size": world});
            let w = weights_to_bytes(&model)?;
            let o = optimizer_to_bytes::<B, _, _>(&optim)?;
            ckpts.save(
                KIND,
                step,
                meta,
                &[("model.safetensors", &w), ("optimizer.bin", &o)],
            )?;
        }
        if stop {
            if lead {
                tracing::info!("tokenizer training stopped at step {step} of {}", tc.steps);
            }
            break;
        }
    }
    let (usage, perplexity) = count_stats(&histogram(&recent, k));
    let info = TokenizerInfo {
        format: "umgen-vq".into(),
        version: 1,
        config: config.clone(),
        raster: [c, h, w],
        steps: step,
        usage,
        perplexity,
    };
    let tokenizer = VqTokenizer::new(info, model.valid(), device.clone());
    if lead {
        tokenizer.save(out)?;
    }
    group.barrier()?;
    Ok(tokenizer)
}

/// Uses per code over the recent steps.
fn histogram(recent: &std::collections::VecDeque<Vec<f64>>, k: usize) -> Vec<f64> {
    let mut h = vec![0.0; k];
    for counts in recent {
        for (a, c) in h.iter_mut().zip(counts) {
            *a += c;
        }
    }
    h
}

fn mismatch(dir: &Path, reason: String) -> VqError {
    VqError::Checkpoint(umgen_checkpoint::CheckpointError::Mismatch {
        path: dir.into(),
        reason,
    })
}

/// Restarts codes unused for `restart_after` steps from random rows of the current batch.
pub fn restart_dead<B: AutodiffBackend>(
    q: crate::quantizer::Quantizer<B>,
    last_used: &[u64],
    step: u64,
    tc: &VqTrainConfig,
    z: Tensor<B, 2>,
    device: &B::Device,
) -> (crate::quantizer::Quantizer<B>, usize) {
    let dead: Vec<i64> = (0..last_used.len())
        .filter(|&i| step.saturating_sub(last_used[i]) >= tc.restart_after)
        .map(|i| i as i64)
        .collect();
    if dead.is_empty() {
        return (q, 0);
    }
    let n = z.dims()[0];
    let mut rng = StdRng::seed_from_u64(tc.seed ^ step.wrapping_mul(0x2545_f491_4f6c_dd1d));
    let rows: Vec<i64> = dead.iter().map(|_| rng.random_range(0..n) as i64).collect();
    let m = dead.len();
    let vectors = z.select(0, Tensor::from_data(TensorData::new(rows, [m]), device));
    (
        q.restart(Tensor::from_data(TensorData::new(dead, [m]), device), vectors),
        m,
    )
}
