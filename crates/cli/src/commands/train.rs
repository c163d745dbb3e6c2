//! `umgen train`: tokenize if needed, then train the backbone.

use crate::cli::TrainArgs;
use crate::device::Device;
use crate::dist::rank_device;
use anyhow::Context;
use burn::tensor::backend::AutodiffBackend;
use std::ops::ControlFlow;
use std::time::Duration;
use umgen::data::{Dataset, TokenSet};
use umgen::dist::DistEnv;
use umgen::train::{RunSpec, train};
use umgen::{UmgenConfig, backbone_spec, tokens_missing};

/// Trains, alone or as one rank of a data-parallel job.
pub fn run(a: &TrainArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let env = DistEnv::from_env()?;
    let lead = env.rank == 0;
    let config = UmgenConfig::load(&a.config.config, &a.config.set)?;
    let device = Device::parse(&rank_device(&a.device, &env))?;
    let (run, tokens) = prepare(&config, device, &env, kinds)?;
    // `train` writes `out_dir/config.json` once the run has passed its checks.
    let tc = &config.train;
    tracing::info!(
        "training {} parameters on {} ({} windows of {} frames × N = {}), {} steps of {} × {} × {} rank(s) into {}",
        run.spec.param_count(&run.backbone),
        tc.tokens.display(),
        tokens.windows(tc.frames + 1, tc.gap, Some(&tc.split)).len(),
        tc.frames + 1,
        run.spec.n,
        tc.steps,
        tc.batch_size,
        tc.grad_accum,
        env.world_size,
        tc.out_dir.display()
    );
    let bar = if lead {
        crate::progress::bar(tc.steps, "steps")?
    } else {
        indicatif::ProgressBar::hidden()
    };
    let identity = run.identity_digest();
    let limit = crate::progress::TimeLimit::minutes(a.time_limit);
    let summary = crate::with_autodiff!(device, |B, dev| {
        let mut group = crate::dist::join::<<B as AutodiffBackend>::InnerBackend>(&env, &identity, &a.dist)?;
        train::<B>(&run, &tokens, &dev, a.resume, group.as_mut(), |r| {
            bar.set_position(r.step);
            if let Some(v) = &r.values {
                bar.set_message(format!("loss {:.4}", v[0].1));
                let line: Vec<String> = v.iter().map(|(k, x)| format!("{k} {x:.4}")).collect();
                bar.suspend(|| {
                    tracing::info!(
                        "step {}/{} ({:.0} ms): {}",
                        r.step,
                        r.steps,
                        1e3 * r.seconds,
                        line.join(", ")
                    )
                });
            }
            // Checked on logging steps, where several ranks exchange rank 0's decision.
            if r.values.is_some() && limit.reached(&bar, r.step) {
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        })?
    });
    bar.finish_and_clear();
    tracing::info!(
        "done at step {}: loss {} → {}; checkpoint {}",
        summary.step,
        summary.first_loss.map_or("-".into(), |v| format!("{v:.4}")),
        summary.last_loss.map_or("-".into(), |v| format!("{v:.4}")),
        summary
            .checkpoint
            .as_ref()
            .map_or("none".into(), |p| p.display().to_string())
    );
    Ok(())
}

/// The run `config` describes and its token cache, tokenizing on rank 0 (of `env`) what the cache lacks of
/// `train.data`, the other ranks waiting for it.
pub fn prepare(
    config: &UmgenConfig,
    device: Device,
    env: &DistEnv,
    kinds: &crate::Kinds,
) -> anyhow::Result<(RunSpec, TokenSet)> {
    let lead = env.rank == 0;
    let registry = config.registry(&kinds.catalog_with(device.codec_loader())?)?;
    let layout = registry.layout()?;
    let tc = &config.train;
    if let (Some(data_dir), false) = (&tc.data, lead) {
        // Rank 0 tokenizes; the others wait for the cache before they meet it (the launcher or the job
        // scheduler stops them if rank 0 fails meanwhile).
        let data = Dataset::open(data_dir)?;
        let mut waited = false;
        while tokens_missing(&data, &tc.tokens, Some(&tc.split))? > 0 {
            if !waited {
                tracing::info!(
                    "rank {}: waiting for rank 0 to tokenize {}",
                    env.rank,
                    data_dir.display()
                );
                waited = true;
            }
            std::thread::sleep(Duration::from_secs(1));
        }
    } else if let Some(data_dir) = &tc.data {
        // Tokenize what is missing; finished shards are skipped.
        let data = Dataset::open(data_dir)?;
        let threads = super::tokenize::default_threads(&[device]);
        // The validation split (`train.val_every`) goes into the same cache; only rank 0 reads it.
        let splits: Vec<&str> = std::iter::once(tc.split.as_str())
            .chain((tc.val_every > 0 && tc.val_split != tc.split).then_some(tc.val_split.as_str()))
            .collect();
        let mut missing = 0;
        for split in &splits {
            missing += tokens_missing(&data, &tc.tokens, Some(split))?;
        }
        // One registry per thread (each loads the tokenizers) only where a split has frames to encode.
        let registries = if missing > 0 {
            super::tokenize::registries(config, &[device], threads, kinds)?
        } else {
            vec![registry.clone()]
        };
        for split in splits {
            let r = super::tokenize::with_progress(&registries, &data, &tc.tokens, Some(split), threads)?;
            if r.written > 0 {
                tracing::info!(
                    "{}: tokenized {} frames of split `{split}` of {}",
                    tc.tokens.display(),
                    r.frames,
                    data_dir.display()
                );
            }
        }
    }
    let tokens = TokenSet::open(&tc.tokens, layout.fingerprint()).with_context(|| {
        format!(
            "token cache {} (set train.data to make it, or run `umgen tokenize`)",
            tc.tokens.display()
        )
    })?;
    let spec = backbone_spec(&registry, &config.backbone)?;
    let run = RunSpec {
        backbone: config.backbone.clone(),
        spec,
        train: tc.clone(),
        fingerprint: layout.fingerprint().into(),
        config: config.to_json(),
    };
    Ok((run, tokens))
}
