//! `umgen bench generate`: generation with the engine (random weights, random valid histories, no rules).
//! Once: the start-up (weights to the device, kernels compiled). Per batch size and history length: the
//! first frame (the decoding steps captured as graphs the first time), then the median of `--frames`
//! frames as ms per token of the whole frame and of the decoding steps alone, the window pass, frames per
//! second, and memory. `torch_umgen.py infer-scaling` reports the first two as `per_token_ms` and
//! `decode_ms_per_token`, `infer-graph` its CUDA-graph step as `graph_ms_per_token`.

use super::engine::AnyEngine;
use crate::cli::{BenchGenerateArgs, DecoderArg};
use crate::device::Device;
use burn::tensor::backend::Backend;
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Backbone;
use umgen::backbone_spec;
use umgen::generate::engine::EngineSettings;
use umgen::generate::{DEFAULT_PASS_FRAMES, FrameControl, Generator, NextFrame, Sampling};

/// One measurement.
struct Row {
    batch: usize,
    t: usize,
    first_s: f64,
    frame_s: f64,
    window_ms: f64,
    step_ms: f64,
}

/// Measures.
pub fn run(a: &BenchGenerateArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    if a.decoder == DecoderArg::Burn {
        for &batch in &a.batch {
            super::bench_generate_burn::run(a, batch, kinds)?;
        }
        return Ok(());
    }
    let (config, path, _) = super::bench::bench_config(&a.model)?;
    let registry = config.registry(&kinds.catalog()?)?;
    let spec = backbone_spec(&registry, &config.backbone)?;
    let cfg = config.backbone.for_inference();
    let device = Device::parse(&a.device)?;
    anyhow::ensure!(
        a.frames >= 1 && !a.batch.is_empty() && a.batch.iter().all(|&b| b >= 1),
        "--frames and every --batch must be at least 1"
    );
    if let Some(t) = a.history.iter().find(|t| **t == 0 || **t > cfg.max_frames) {
        anyhow::bail!(
            "--history {t}: must be 1..={} (backbone.max_frames; raise it with --set backbone.max_frames=20)",
            cfg.max_frames
        );
    }
    let window = a.history.iter().copied().max().unwrap_or(1);
    let n = spec.n;
    let started = Instant::now();
    <burn::backend::Flex as Backend>::seed(&Default::default(), 0);
    let model = Backbone::<burn::backend::Flex>::new(&cfg, &spec, &Default::default())?;
    let (plain, slots) = (model.plain(), model.slots());
    let weights = match a.check {
        0 => None,
        _ => Some(umgen::checkpoint::burn_io::weights_to_bytes(&model)?),
    };
    drop(model);
    let built_s = started.elapsed().as_secs_f64();
    let settings = |sampling| EngineSettings {
        sampling: vec![sampling; spec.segments.len()],
        window,
        seed: 0,
        pass_frames: DEFAULT_PASS_FRAMES,
    };
    let started = Instant::now();
    let mut e = AnyEngine::new(device, &plain, settings(Sampling::default()), a.precision)?.timed(true);
    let start_s = started.elapsed().as_secs_f64();
    let check = match weights {
        Some(bytes) => {
            let (batch, t) = (a.batch[0], a.history.first().copied().unwrap_or(1));
            let h = super::bench_generate_burn::history(&spec, &slots, batch, t);
            let mut greedy = AnyEngine::new(device, &plain, settings(Sampling::greedy()), a.precision)?;
            let ours = roll(&mut greedy, h.clone(), a.check)?;
            drop(greedy);
            let theirs = crate::with_inference!(device, |I, dev| {
                let model = Backbone::<I>::new(&cfg, &spec, &dev)?;
                let model =
                    umgen::checkpoint::burn_io::weights_from_bytes(model, bytes, "the engine's weights")?;
                let mut g = Generator::new(&model, vec![Sampling::greedy(); spec.segments.len()], window, 0)?;
                roll(&mut g, h, a.check)?
            });
            Some(agreement(&ours, &theirs))
        }
        None => None,
    };
    drop(plain);
    tracing::info!("random weights in {built_s:.1} s; engine ready in {start_s:.1} s");
    let control = FrameControl::default();
    let mut rows = Vec::new();
    for &batch in &a.batch {
        for &t in &a.history {
            let h = super::bench_generate_burn::history(&spec, &slots, batch, t);
            let t0 = Instant::now();
            e.next_frame(&h, &control)?;
            let first_s = t0.elapsed().as_secs_f64();
            let before = e.times();
            let mut times = Vec::with_capacity(a.frames);
            for _ in 0..a.frames {
                let t0 = Instant::now();
                e.next_frame(&h, &control)?;
                times.push(t0.elapsed().as_secs_f64());
            }
            times.sort_by(f64::total_cmp);
            let after = e.times();
            let per = a.frames as f64;
            let row = Row {
                batch,
                t,
                first_s,
                frame_s: times[times.len() / 2],
                window_ms: 1e3 * (after.window - before.window) / per,
                step_ms: 1e3 * (after.decode - before.decode) / (after.steps - before.steps).max(1) as f64,
            };
            tracing::info!(
                "batch {batch}, T = {t}: first frame {first_s:.2} s, {:.3} ms/token, step {:.3} ms",
                1e3 * row.frame_s / n as f64,
                row.step_ms
            );
            rows.push(row);
        }
    }
    let profile = if a.profile {
        let (batch, t) = (a.batch[a.batch.len() - 1], a.history.last().copied().unwrap_or(1));
        let h = super::bench_generate_burn::history(&spec, &slots, batch, t);
        e = e.profiled(true);
        e.next_frame(&h, &control)?;
        let window = e.window_profile();
        e = e.profiled(false);
        Some((batch, t, window, e.profile_step(50)?))
    } else {
        None
    };
    let rollout = if a.rollout > 0 {
        let (batch, t) = (a.batch[0], a.history.first().copied().unwrap_or(1));
        let mut h = super::bench_generate_burn::history(&spec, &slots, batch, t);
        let t0 = Instant::now();
        for _ in 0..a.rollout {
            let next = e.next_frame(&h, &control)?;
            for (scene, f) in h.iter_mut().zip(next) {
                scene.push(f);
            }
        }
        Some((batch, t, t0.elapsed().as_secs_f64()))
    } else {
        None
    };
    let gib = |b: usize| b as f64 / (1u64 << 30) as f64;
    if let Some((tokens, total, frames, all)) = check {
        writeln!(
            std::io::stdout(),
            "check    greedy frames, engine against the burn decoder: {tokens} of {total} tokens and {frames} of {all} frames agree"
        )?;
    }
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "config   {} (N = {n}, d {}, TAR {} + OAR {}, window {window}); decoder engine on {}",
        path.display(),
        cfg.d_model,
        cfg.tar_layers,
        cfg.oar_layers,
        a.device
    )?;
    writeln!(
        out,
        "start    {start_s:.2} s (weights to the device, kernels compiled); engine buffers {:.2} GiB{}",
        gib(e.bytes()),
        e.device_memory().map_or(String::new(), |b| format!(
            "; device memory in use {:.2} GiB",
            gib(b)
        ))
    )?;
    writeln!(
        out,
        "{:>5} {:>4} {:>13} {:>10} {:>10} {:>15} {:>11} {:>10}",
        "batch", "T", "first frame s", "frame s", "ms/token", "step ms/token", "window ms", "frames/s"
    )?;
    for r in &rows {
        writeln!(
            out,
            "{:>5} {:>4} {:>13.2} {:>10.3} {:>10.4} {:>15.4} {:>11.1} {:>10.2}",
            r.batch,
            r.t,
            r.first_s,
            r.frame_s,
            1e3 * r.frame_s / n as f64,
            r.step_ms,
            r.window_ms,
            r.batch as f64 / r.frame_s
        )?;
    }
    if let Some((batch, t, mut window, step)) = profile {
        window.sort_by(|x, y| y.1.total_cmp(&x.1));
        let total: f64 = window.iter().map(|w| w.1).sum();
        writeln!(
            out,
            "window pass, batch {batch}, T = {t}, each operation waited for: {:.1} ms",
            1e3 * total
        )?;
        for (name, s, count) in &window {
            writeln!(out, "  {name:<28} {:>9.2} ms {count:>6} ×", 1e3 * s)?;
        }
        let total: f64 = step.iter().filter(|s| s.2).map(|s| s.1).sum();
        writeln!(
            out,
            "decoding step, each operation alone (50 in a graph): {total:.1} µs"
        )?;
        for (name, us, in_step) in &step {
            let note = if *in_step { "" } else { " (not in the step)" };
            writeln!(out, "  {name:<28} {us:>9.2} µs{note}")?;
        }
    }
    if let Some((batch, t, s)) = rollout {
        writeln!(
            out,
            "rollout  {} frames × {batch} scene(s) from T = {t}: {s:.1} s ({:.2} s a frame)",
            a.rollout,
            s / a.rollout as f64
        )?;
    }
    writeln!(
        out,
        "first frame: the first at that batch and T (the steps' graphs captured at the first of a batch size). \
         ms/token: median frame / N. step ms/token: the N decoding steps alone, per step of the batch. \
         window: ego module, TAR and keep logits per frame. frames/s: frames of the whole batch per second."
    )?;
    Ok(())
}

/// `frames` more frames of every scene of `history` from `g`, without rules; the new frames.
fn roll(
    g: &mut dyn NextFrame,
    mut history: Vec<Vec<Vec<u32>>>,
    frames: usize,
) -> anyhow::Result<Vec<Vec<Vec<u32>>>> {
    let start = history.first().map_or(0, Vec::len);
    for _ in 0..frames {
        let next = g.next_frame(&history, &FrameControl::default())?;
        for (scene, f) in history.iter_mut().zip(next) {
            scene.push(f);
        }
    }
    Ok(history.into_iter().map(|s| s[start..].to_vec()).collect())
}

/// Tokens that agree, tokens, frames that agree, frames.
fn agreement(a: &[Vec<Vec<u32>>], b: &[Vec<Vec<u32>>]) -> (usize, usize, usize, usize) {
    let frames: Vec<(&Vec<u32>, &Vec<u32>)> = a.iter().zip(b).flat_map(|(x, y)| x.iter().zip(y)).collect();
    let tokens = frames
        .iter()
        .map(|(x, y)| x.iter().zip(*y).filter(|(p, q)| p == q).count())
        .sum();
    let total = frames.iter().map(|(x, _)| x.len()).sum();
    let same = frames.iter().filter(|(x, y)| x == y).count();
    (tokens, total, same, frames.len())
}
