//! `umgen bench generate --decoder burn`: what one new frame costs per token as the history grows with the
//! burn decoder, and for a vanilla autoregressive transformer over all frames' tokens (the paper's Fig. 7
//! comparison).

use crate::cli::BenchGenerateArgs;
use crate::device::{Device, memory_in_use};
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Tensor};
use rand::{Rng, SeedableRng, rngs::StdRng};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::{Backbone, BackboneSpec, Slot, VanillaAr};
use umgen::backbone_spec;
use umgen::generate::{FrameControl, Generator, Sampling};

/// Random valid frames `[batch][t][N]`.
pub(super) fn history(
    model_spec: &BackboneSpec,
    slots: &[Slot],
    batch: usize,
    t: usize,
) -> Vec<Vec<Vec<u32>>> {
    let mut rng = StdRng::seed_from_u64(7);
    (0..batch)
        .map(|_| {
            (0..t)
                .map(|_| {
                    slots
                        .iter()
                        .map(|s| match *s {
                            Slot::Start(i) => model_spec.segments[i].vocab as u32,
                            Slot::End(i) => model_spec.segments[i].vocab as u32 + 1,
                            Slot::Content(i, _) => rng.random_range(0..model_spec.segments[i].vocab as u32),
                        })
                        .collect()
                })
                .collect()
        })
        .collect()
}

/// One row of the table.
struct Row {
    t: usize,
    ours_ms: f64,
    ours_peak: u64,
    vanilla_ms: f64,
    vanilla_peak: u64,
    vanilla_cache: u64,
}

/// Measures at `batch` scenes.
pub fn run(a: &BenchGenerateArgs, batch: usize, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let (config, path, _) = super::bench::bench_config(&a.model)?;
    let registry = config.registry(&kinds.catalog()?)?;
    let spec = backbone_spec(&registry, &config.backbone)?;
    let cfg = &config.backbone.for_inference();
    let device = Device::parse(&a.device)?;
    let on_gpu = matches!(device, Device::Cuda(_));
    let n = spec.n;
    // "Same total depth" as the PyTorch reference counts it: every attention layer of the model.
    let depth = cfg.ego_hist_layers + cfg.ego_env_layers + 2 * cfg.tar_layers + cfg.oar_layers;
    let vocab = spec.segments.iter().map(|s| s.vocab).max().unwrap_or(1);
    anyhow::ensure!(
        batch >= 1 && a.tokens >= 1 && a.frames >= 1,
        "--batch, --tokens and --frames must be at least 1"
    );
    if let Some(t) = a.history.iter().find(|t| **t == 0 || **t > cfg.max_frames) {
        anyhow::bail!(
            "--history {t}: must be 1..={} (backbone.max_frames; raise it with --set backbone.max_frames=20)",
            cfg.max_frames
        );
    }
    let rows = crate::with_inference!(device, |I, dev| {
        let sync = || <I as Backend>::sync(&dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"));
        <I as Backend>::seed(&dev, 0);
        let model = Backbone::<I>::new(cfg, &spec, &dev)?;
        let vanilla = VanillaAr::<I>::new(
            cfg.d_model,
            cfg.heads,
            cfg.mlp_ratio,
            depth,
            vocab,
            cfg.precision,
            &dev,
        );
        let slots = model.slots();
        let sampling = vec![Sampling::default(); spec.segments.len()];
        let mut rows = Vec::new();
        for &t in &a.history {
            let h = history(&spec, &slots, batch, t);
            let mut g = Generator::new(&model, sampling.clone(), t, 0)?
                .draw_on_device(a.draw.on_device(on_gpu, batch))
                .device_top_k(a.device_top_k.into())
                .speculate(a.speculate);
            // The first frame compiles kernels (CUDA) and warms caches.
            let t0 = Instant::now();
            g.next_frame(&h, &FrameControl::default())?;
            sync()?;
            tracing::info!(
                "T = {t}: first frame (compiles kernels) {:.1} s",
                t0.elapsed().as_secs_f64()
            );
            // The median of a few frames: single frames of a small model are noisy on a shared CPU.
            let mut times = Vec::new();
            for _ in 0..a.frames {
                let t0 = Instant::now();
                g.next_frame(&h, &FrameControl::default())?;
                sync()?;
                times.push(1e3 * t0.elapsed().as_secs_f64() / n as f64);
            }
            times.sort_by(f64::total_cmp);
            let ours_ms = times[times.len() / 2];
            let ours_peak = memory_in_use(device);
            // Logged as measured, so that a run cut short still tells what it got.
            tracing::info!("T = {t}: TAR/OAR {ours_ms:.3} ms/token");
            // The vanilla model decodes frame t + 1 after t·N cached tokens.
            let mut rng = StdRng::seed_from_u64(3);
            let step = |cache: &mut _, rng: &mut StdRng| -> anyhow::Result<()> {
                let x = Tensor::<I, 2>::random([batch, cfg.d_model], Distribution::Normal(0.0, 1.0), &dev);
                let logits = vanilla.step(x, cache)?;
                let host: Vec<f32> = logits.into_data().iter::<f32>().collect();
                for row in host.chunks(vocab) {
                    Sampling::default().draw(row, rng);
                }
                Ok(())
            };
            // A fresh cache per run, with room for its --tokens steps only: attention covers the whole
            // fixed-size cache, so spare room would count as history.
            let fresh = || vanilla.filled_cache(batch, t * n, a.tokens, cfg.heads, &dev);
            let mut cache = fresh();
            step(&mut cache, &mut rng)?;
            sync()?;
            let mut times = Vec::new();
            for _ in 0..5 {
                cache = fresh();
                sync()?;
                let t0 = Instant::now();
                for _ in 0..a.tokens {
                    step(&mut cache, &mut rng)?;
                }
                sync()?;
                times.push(1e3 * t0.elapsed().as_secs_f64() / a.tokens as f64);
            }
            times.sort_by(f64::total_cmp);
            let vanilla_ms = times[times.len() / 2];
            let vanilla_peak = memory_in_use(device);
            tracing::info!("T = {t}: vanilla AR {vanilla_ms:.3} ms/token");
            let vanilla_cache = (depth * 2 * batch * (t * n + a.tokens) * cfg.d_model * 4) as u64;
            rows.push(Row {
                t,
                ours_ms,
                ours_peak,
                vanilla_ms,
                vanilla_peak,
                vanilla_cache,
            });
            drop(cache);
        }
        rows
    });
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "config   {} (N = {n}, d {}, TAR {} + OAR {}; vanilla AR depth {depth})",
        path.display(),
        cfg.d_model,
        cfg.tar_layers,
        cfg.oar_layers
    )?;
    writeln!(out, "device   {}, batch {}", a.device, batch)?;
    writeln!(
        out,
        "{:>4} {:>16} {:>18} {:>16} {:>18} {:>16} {:>16}",
        "T",
        "TAR/OAR ms/tok",
        "TAR/OAR mem GiB",
        "vanilla ms/tok",
        "vanilla mem GiB",
        "vanilla KV GiB",
        "TAR/OAR frames/s"
    )?;
    for r in rows {
        writeln!(
            out,
            "{:>4} {:>16.3} {:>18} {:>16.3} {:>18} {:>16.3} {:>16.3}",
            r.t,
            r.ours_ms,
            if r.ours_peak > 0 {
                format!("{:.2}", gib(r.ours_peak))
            } else {
                "-".into()
            },
            r.vanilla_ms,
            if r.vanilla_peak > 0 {
                format!("{:.2}", gib(r.vanilla_peak))
            } else {
                "-".into()
            },
            gib(r.vanilla_cache),
            // A new frame for every scene of the batch takes N steps.
            1e3 * batch as f64 / (r.ours_ms * n as f64)
        )?;
    }
    writeln!(
        out,
        "ms/tok: median of --frames new frames of N tokens (ego action, TAR over T frames, N OAR steps with sampling) / N; vanilla: median of 5 runs of --tokens decode steps after T·N cached tokens, with sampling. mem: device pool after the measurement (CUDA only). frames/s: new frames of the whole batch per second."
    )?;
    Ok(())
}
