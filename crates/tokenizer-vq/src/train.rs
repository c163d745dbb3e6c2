//! Training a VQ tokenizer: AdamW with warm-up + cosine, global-norm clipping, EMA codebook with dead-code
//! restarts, checkpoints and TensorBoard scalars; resumable from the last good checkpoint.

use crate::config::{VqConfig, VqTrainConfig};
use crate::error::{Result, VqError};
use crate::loss::{commitment, reconstruction};
use crate::metrics::code_stats;
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
use umgen_metrics::MetricLog;
use umgen_optim::{Schedule, clip_grad_norm};

/// Checkpoint kind of tokenizer runs.
pub const KIND: &str = "vq-tokenizer";
/// Steps between checks for dead codes.
const RESTART_CHECK: u64 = 10;

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
    mut on_step: impl FnMut(&StepReport) -> ControlFlow<()>,
) -> Result<VqTokenizer<B::InnerBackend>> {
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
        .with_epsilon(1e-8)
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
        tracing::info!(
            "resuming tokenizer training from {} (step {step})",
            l.dir.display()
        );
    }
    let mut log = MetricLog::open(out).map_err(|error| VqError::Metrics {
        path: out.into(),
        error,
    })?;
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
    let batch = |s: u64| -> Result<Tensor<B, 4>> {
        let data = render(
            source,
            &batch_indices(source.len(), tc.seed, s, tc.batch_size),
            threads,
        )?;
        Ok(Tensor::from_data(
            TensorData::new(data, [tc.batch_size, c, h, w]),
            device,
        ))
    };
    if step == 0 {
        // Start the codebook on encoder outputs of the first batch, so that every code is near data.
        let (rows, _) = model.encode_rows(batch(0)?);
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
    let mut recent: Vec<u32> = Vec::new();
    while step < tc.steps {
        let t0 = Instant::now();
        let x = batch(step)?;
        let fwd = model.forward(x.clone());
        let rec = reconstruction(config.output, &tc.loss, fwd.recon, x);
        let commit = commitment(fwd.quantized.z.clone(), fwd.quantized.z_q.clone());
        let loss = rec.total.clone() + commit.clone().mul_scalar(tc.loss.commitment);
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        let grad_norm = clip_grad_norm::<B, _>(&model, &mut grads, tc.grad_clip);
        let lr = schedule.lr(step);
        model = optim.step(lr, model, grads);
        let z = fwd.quantized.z.detach();
        let ids: Vec<u32> = fwd
            .quantized
            .indices
            .clone()
            .into_data()
            .iter::<i64>()
            .map(|i| i as u32)
            .collect();
        model.quantizer = model
            .quantizer
            .ema_update(z.clone(), fwd.quantized.indices, tc.ema_decay);
        step += 1;
        for &i in &ids {
            last_used[i as usize] = step;
        }
        if step.is_multiple_of(RESTART_CHECK) {
            model.quantizer = restart_dead(model.quantizer, &last_used, step, tc, z, device);
        }
        recent.extend_from_slice(&ids);
        let keep = 8 * ids.len();
        if recent.len() > keep {
            recent.drain(..recent.len() - keep);
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
            let mut got: Vec<f64> = Tensor::cat(parts, 0).into_data().iter::<f64>().collect();
            let grad_norm = got.pop().unwrap_or(f64::NAN);
            let (usage, ppl) = code_stats(&recent, k);
            let secs = t0.elapsed().as_secs_f64();
            let mut v: Vec<(&'static str, f64)> = names.into_iter().zip(got).collect();
            v.extend([
                ("codebook/usage", usage),
                ("codebook/perplexity", ppl),
                ("lr", lr),
                ("grad_norm", grad_norm),
                ("rasters_per_s", tc.batch_size as f64 / secs),
            ]);
            log.log(step, &v)
                .and_then(|()| log.flush())
                .map_err(|error| VqError::Metrics {
                    path: out.into(),
                    error,
                })?;
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
        if stop || step.is_multiple_of(tc.checkpoint_every.max(1)) || step == tc.steps {
            let meta = serde_json::json!({"config": config, "train": tc, "last_used": last_used});
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
            tracing::info!("tokenizer training stopped at step {step} of {}", tc.steps);
            break;
        }
    }
    let (usage, perplexity) = code_stats(&recent, k);
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
    tokenizer.save(out)?;
    Ok(tokenizer)
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
) -> crate::quantizer::Quantizer<B> {
    let dead: Vec<i64> = (0..last_used.len())
        .filter(|&i| step.saturating_sub(last_used[i]) >= tc.restart_after)
        .map(|i| i as i64)
        .collect();
    if dead.is_empty() {
        return q;
    }
    let n = z.dims()[0];
    let mut rng = StdRng::seed_from_u64(tc.seed ^ step.wrapping_mul(0x2545_f491_4f6c_dd1d));
    let rows: Vec<i64> = dead.iter().map(|_| rng.random_range(0..n) as i64).collect();
    let m = dead.len();
    let vectors = z.select(0, Tensor::from_data(TensorData::new(rows, [m]), device));
    q.restart(Tensor::from_data(TensorData::new(dead, [m]), device), vectors)
}
