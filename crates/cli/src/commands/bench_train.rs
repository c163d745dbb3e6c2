//! `umgen bench train`: the training step on random tokens, for speed and memory.

use crate::cli::BenchTrainArgs;
use crate::device::Device;
use burn::optim::{AdamWConfig, GradientsParams, Optimizer};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::{Backbone, BackboneSpec};
use umgen::{UmgenConfig, backbone_spec, builtin_catalog};

/// Random windows `[b, f, N]` with every id valid at its position.
fn random_tokens<B: AutodiffBackend>(
    spec: &BackboneSpec,
    b: usize,
    f: usize,
    dev: &B::Device,
) -> Tensor<B, 3, Int> {
    let mut rng = StdRng::seed_from_u64(0);
    let mut ids = Vec::with_capacity(b * f * spec.n);
    for _ in 0..b * f {
        for s in &spec.segments {
            for p in 0..s.block_len {
                let at = s.block_start + p;
                ids.push(if at < s.offset {
                    s.vocab as i64
                } else if at >= s.offset + s.tokens {
                    s.vocab as i64 + 1
                } else {
                    rng.random_range(0..s.vocab as i64)
                });
            }
        }
    }
    Tensor::from_data(TensorData::new(ids, [b, f, spec.n]), dev)
}

/// Measures.
pub fn run(a: &BenchTrainArgs) -> anyhow::Result<()> {
    // Speed does not depend on trained tokenizers; codebook sizes come from the config.
    let (config, _) = UmgenConfig::load(&a.config.config, &a.config.set)?.without_missing_tokenizers();
    let registry = config.registry(&builtin_catalog()?)?;
    let spec = backbone_spec(&registry, &config.backbone)?;
    let (cfg, tc) = (&config.backbone, &config.train);
    let device = Device::parse(&a.device)?;
    let (b, f) = (tc.batch_size, tc.frames + 1);
    let tokens_per_step = (b * tc.frames * spec.n) as f64;
    let flops = spec.train_flops(cfg, b, tc.frames);
    let (median, peak) = crate::with_autodiff!(device, |B, dev| {
        B::seed(&dev, 0);
        let mut model = Backbone::<B>::new(cfg, &spec, &dev)?;
        let mut optim = AdamWConfig::new()
            .with_weight_decay(tc.weight_decay as f32)
            .init();
        let batch = random_tokens::<B>(&spec, b, f, &dev);
        let mut times = Vec::new();
        let mut peak = 0u64;
        for i in 0..a.warmup + a.steps {
            let t0 = Instant::now();
            let losses = model.loss(batch.clone(), tc.ego_loss_weight)?;
            let loss = losses.total.clone();
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            model = optim.step(tc.lr, model, grads);
            // Wait for the step's work on the device before reading the clock.
            B::sync(&dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"))?;
            peak = peak.max(crate::device::memory_in_use(device));
            if i >= a.warmup {
                times.push(t0.elapsed().as_secs_f64());
            }
        }
        times.sort_by(f64::total_cmp);
        (times[times.len() / 2], peak)
    });
    let mut out = std::io::stdout().lock();
    writeln!(out, "config        {}", a.config.config.display())?;
    writeln!(out, "device        {}", a.device)?;
    writeln!(
        out,
        "parameters    {} ({:.1} M)",
        spec.param_count(cfg),
        spec.param_count(cfg) as f64 / 1e6
    )?;
    writeln!(
        out,
        "batch         {b} windows × {} frames × N {} = {} tokens/step",
        tc.frames, spec.n, tokens_per_step
    )?;
    writeln!(
        out,
        "step          {:.1} ms (median of {})",
        1e3 * median,
        a.steps
    )?;
    writeln!(out, "throughput    {:.0} tokens/s", tokens_per_step / median)?;
    writeln!(
        out,
        "compute       {:.2} TFLOP/step, {:.1} TFLOP/s, MFU {:.1}% of {} TFLOP/s",
        flops / 1e12,
        flops / median / 1e12,
        100.0 * flops / median / (a.peak_tflops * 1e12),
        a.peak_tflops
    )?;
    if peak > 0 {
        writeln!(
            out,
            "peak memory   {:.2} GiB reserved",
            peak as f64 / (1u64 << 30) as f64
        )?;
    } else {
        writeln!(out, "peak memory   not measured on this device")?;
    }
    Ok(())
}
