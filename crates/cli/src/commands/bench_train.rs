//! `umgen bench train`: the training step on random tokens, for speed and memory.

use crate::cli::BenchTrainArgs;
use crate::device::Device;
use crate::dist::{DistBackend, rank_device};
use anyhow::Context;
use burn::optim::GradientsParams;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::{Backbone, BackboneSpec, Kernels, LossOptions};
use umgen::backbone_spec;
use umgen::dist::{DistEnv, Overlap, ProcessGroup, Shards, broadcast_module};
use umgen::optim::FusedAdamW;

/// The median of `times` (the upper one of an even count), `None` for none.
pub fn median(mut times: Vec<f64>) -> Option<f64> {
    times.sort_by(f64::total_cmp);
    times.get(times.len() / 2).copied()
}

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

/// Every rank's `value` (each rank's own, in rank order), on rank 0 and the others.
fn per_rank<B: Backend>(
    group: &mut dyn ProcessGroup<B>,
    value: f64,
    device: &B::Device,
) -> anyhow::Result<Vec<f64>> {
    let (rank, world) = (group.rank(), group.world_size());
    let mut mine = vec![0.0f32; world];
    mine[rank] = value as f32;
    let mean = group.all_reduce_mean(Tensor::from_floats(mine.as_slice(), device))?;
    Ok(mean.into_data().iter::<f64>().map(|m| m * world as f64).collect())
}

/// Measures.
pub fn run(a: &BenchTrainArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    run_with(a, kinds, &mut NoHooks)
}

/// What a developer tool adds to the timed steps (`umgen-kernel-bench train`: kernel settings taking turns,
/// a profile of the host); the defaults add nothing.
pub trait StepHooks {
    /// Values the steps take turns between (1: one).
    fn turns(&self) -> usize {
        1
    }

    /// Before step `i` (warm-up steps included): the turn it runs under.
    fn before_step(&mut self, i: usize) -> anyhow::Result<usize> {
        let _ = i;
        Ok(0)
    }

    /// The kernels of turn `turn`, given the run's (`base`).
    fn kernels(&self, turn: usize, base: &Kernels) -> Kernels {
        let _ = turn;
        *base
    }

    /// When the timed steps start (`true`) and when they end.
    fn timed(&mut self, start: bool) -> anyhow::Result<()> {
        let _ = start;
        Ok(())
    }

    /// After the report's step line: what the turns measured, from each turn's step times in seconds.
    fn report(&self, out: &mut dyn Write, by_turn: &[Vec<f64>]) -> anyhow::Result<()> {
        let _ = (out, by_turn);
        Ok(())
    }
}

/// No hooks: `umgen bench train` itself.
pub struct NoHooks;

impl StepHooks for NoHooks {}

/// [`run`] with `hooks` around its steps.
pub fn run_with(a: &BenchTrainArgs, kinds: &crate::Kinds, hooks: &mut dyn StepHooks) -> anyhow::Result<()> {
    let (config, path, _) = super::bench::bench_config(&a.model)?;
    let registry = config.registry(&kinds.catalog()?)?;
    let spec = backbone_spec(&registry, &config.backbone)?;
    let (cfg, tc) = (&config.backbone, &config.train);
    let env = DistEnv::from_env()?;
    let device = Device::parse(&rank_device(&a.device, &env))?;
    let world = env.world_size;
    let (b, f) = (tc.batch_size, tc.frames + 1);
    let tokens_per_step = (b * tc.frames * spec.n * world) as f64;
    let flops = spec.train_flops(cfg, b, tc.frames) * world as f64;
    let bucket = (tc.bucket_mib * 1048576.0) as usize;
    anyhow::ensure!(a.steps >= 1, "--steps 0: give one timed step or more");
    let turns = hooks.turns();
    anyhow::ensure!(
        a.warmup >= turns || turns == 1,
        "the steps take turns between {turns} values: give --warmup {turns} or more, so that each \
         compiles its kernels before the timed steps"
    );
    let loss_options = tc.loss_options()?;
    // Every rank runs the same binary, so std's hasher is stable enough to compare configs.
    let identity = {
        use std::hash::{Hash, Hasher};
        let mut h = std::collections::hash_map::DefaultHasher::new();
        config.to_json().to_string().hash(&mut h);
        format!("{:016x}", h.finish())
    };
    let (median, peak, backend, phases, first, by_turn) = crate::with_autodiff!(device, |B, dev| {
        let mut group =
            <<B as AutodiffBackend>::InnerBackend as DistBackend>::join(&env, &identity, &a.dist)?;
        B::seed(&dev, 0);
        let model = Backbone::<B>::new(cfg, &spec, &dev)?;
        let mut model = broadcast_module(model, group.as_mut(), bucket)?;
        // The trainer's optimizer and clipping, so that the step is the one a run takes.
        type Inner<B> = <B as AutodiffBackend>::InnerBackend;
        // Each turn's kernels and the optimizer's multi-tensor kernels for them, made once.
        let by_turn_kernels: Vec<_> = (0..turns)
            .map(|t| {
                let k = hooks.kernels(t, &tc.kernels);
                (k, umgen::ops::adamw::kernels::<Inner<B>>(&k))
            })
            .collect();
        let mut optim = FusedAdamW::<_, B>::new(tc.adamw_settings()?)
            .with_kernels(umgen::ops::adamw::kernels::<Inner<B>>(&tc.kernels));
        // `train.shard_optimizer`: each rank steps its share and sends it to the others, as in a run.
        let shards = (tc.shard_optimizer && world > 1).then(|| Shards::plan::<B, _>(&model, env.rank, world));
        optim.set_owned(shards.as_ref().map(Shards::owned));
        let batch = random_tokens::<B>(&spec, b, f, &dev);
        let mut times = Vec::new();
        let mut by_turn = vec![Vec::new(); turns];
        let mut phases: [Vec<f64>; 4] = Default::default();
        // The timed steps' host time per phase (no sync: how long the host took to queue it), then its wait
        // for the device at the step's end.
        let mut host: [Vec<f64>; 5] = Default::default();
        // What cubecl's device thread did for the host (`device::device_thread`) at the timed steps' start
        // and end.
        let mut counts = [[(0u64, 0.0f64); 2]; 2];
        // The first step compiles (and autotunes) every kernel on CUDA: it is synced after each phase too,
        // so that its cost is reported apart and split by phase.
        let mut first = [0.0f64; 4];
        let (mut peak, mut live) = (0u64, 0u64);
        // The live set's peak in each phase of the last warmup step (synced after each phase), read at
        // every allocation: too slow for a timed step.
        let mut peaks = [0u64; 4];
        let sync = || B::sync(&dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"));
        // Timed steps first, then (with --phases) as many steps with a sync after every phase.
        let phase_steps = if a.phases { a.steps } else { 0 };
        for i in 0..a.warmup + a.steps + phase_steps {
            let split = i >= a.warmup + a.steps;
            let probe = a.warmup >= 1 && i + 1 == a.warmup;
            let synced = split || i == 0 || probe;
            let turn = hooks.before_step(i)?;
            let kernels = match by_turn_kernels.get(turn) {
                Some((k, adamw)) if turns > 1 => {
                    optim.set_kernels(adamw.clone());
                    *k
                }
                _ => tc.kernels,
            };
            if i == a.warmup {
                counts[0] = crate::device::device_thread(device);
                hooks.timed(true)?;
            }
            if probe {
                // The previous step ended with a sync: nothing of it is left to allocate.
                crate::device::peak_in_use(device, true);
            }
            let mut mark = Instant::now();
            let t0 = mark;
            let mut lap = |k: usize| -> anyhow::Result<()> {
                if synced {
                    sync()?;
                    // Live memory peaks when the forward pass has saved everything the backward pass needs.
                    if k == 0 {
                        live = live.max(crate::device::memory(device).in_use);
                    }
                    if probe {
                        peaks[k] = crate::device::peak_in_use(device, k + 1 < peaks.len());
                    }
                    let s = mark.elapsed().as_secs_f64();
                    if i == 0 {
                        first[k] = s;
                    } else if split {
                        phases[k].push(s);
                    }
                    mark = Instant::now();
                } else if i >= a.warmup {
                    host[k].push(mark.elapsed().as_secs_f64());
                    mark = Instant::now();
                }
                Ok(())
            };
            // The loss as the trainer takes it (prior drop, ordinal smoothing): the step a run would take.
            let options = LossOptions {
                kernels,
                ..loss_options
            };
            // With several ranks, the trainer's overlapped all-reduce: each block's bucket starts as the
            // backward pass completes it.
            let overlap = (world > 1).then(|| {
                Overlap::<B>::new(
                    &model,
                    &model.ready_groups(),
                    GradientsParams::new(),
                    group.as_ref(),
                    bucket,
                )
            });
            let points = overlap.as_ref().map(|o| o.points());
            let losses = model.loss_marked(batch.clone(), options, points.as_ref())?;
            let loss = losses.total.clone();
            if synced {
                // Only a read of the loss makes the lazy graph run before the backward pass.
                drop(loss.clone().into_data());
            }
            lap(0)?;
            // The loss guards the step as in `umgen train`.
            let guard = loss.clone().inner().reshape([1]);
            let grads = loss.backward();
            lap(1)?;
            let grads = match overlap {
                Some(o) => o.finish(grads, group.as_mut())?,
                None => GradientsParams::from_grads(grads, &model),
            };
            lap(2)?;
            model = optim
                .step_clipped(tc.lr, model, grads, tc.grad_clip, Some(guard))
                .module;
            if let Some(s) = &shards {
                model = s.gather::<B, _>(model, group.as_mut())?;
            }
            lap(3)?;
            // Wait for the step's work on the device before reading the clock.
            let queued = t0.elapsed().as_secs_f64();
            sync()?;
            if i >= a.warmup && !synced {
                host[4].push(t0.elapsed().as_secs_f64() - queued);
            }
            peak = peak.max(crate::device::memory(device).reserved);
            let took = t0.elapsed().as_secs_f64();
            if env.rank == 0 {
                tracing::info!(
                    "step {} of {}: {took:.3} s",
                    i + 1,
                    a.warmup + a.steps + phase_steps
                );
            }
            if i + 1 == a.warmup + a.steps {
                counts[1] = crate::device::device_thread(device);
                hooks.timed(false)?;
            }
            if i >= a.warmup && !split {
                times.push(took);
                by_turn[turn].push(took);
            }
        }
        let lives = per_rank::<Inner<B>>(group.as_mut(), live as f64 / (1u64 << 30) as f64, &dev)?;
        group.barrier()?;
        group.finish();
        let phases = phases.map(median);
        let host = host.map(median);
        let steps = a.steps.max(1) as f64;
        let per_step = |k: usize| {
            let ((n0, s0), (n1, s1)) = (counts[0][k], counts[1][k]);
            ((n1 - n0) as f64 / steps, (s1 - s0) / steps)
        };
        let calls = (per_step(0), per_step(1));
        (
            median(times),
            (peak, live, lives, peaks),
            group.backend(),
            (phases, host, calls),
            first,
            by_turn,
        )
    });
    if env.rank != 0 {
        return Ok(());
    }
    let median = median.context("no timed step ran")?;
    let mut out = std::io::stdout().lock();
    match a.model.preset {
        Some(p) => writeln!(out, "preset        {} ({})", p.name(), path.display())?,
        None => writeln!(out, "config        {}", path.display())?,
    }
    writeln!(out, "device        {}", a.device)?;
    super::bench_train_settings::write(&mut out, &device, tc, world, backend)?;
    writeln!(
        out,
        "parameters    {} ({:.1} M)",
        spec.param_count(cfg),
        spec.param_count(cfg) as f64 / 1e6
    )?;
    writeln!(
        out,
        "batch         {b} windows × {} frames × N {} × {world} rank(s) = {} tokens/step",
        tc.frames, spec.n, tokens_per_step
    )?;
    let cuda = matches!(device, Device::Cuda(_));
    writeln!(
        out,
        "first step    {:.1} s (forward {:.1} s, backward {:.1} s, all-reduce {:.1} s, optimizer {:.1} s){}",
        first.iter().sum::<f64>(),
        first[0],
        first[1],
        first[2],
        first[3],
        if cuda {
            ": kernel compilation and autotuning"
        } else {
            ""
        }
    )?;
    writeln!(
        out,
        "step          {:.1} ms (median of {})",
        1e3 * median,
        a.steps
    )?;
    hooks.report(&mut out, &by_turn)?;
    let (phases, host, calls) = phases;
    if let [Some(f), Some(b), Some(r), Some(o), Some(w)] = host {
        // On CUDA, how much of that the host spent in calls on cubecl's device thread.
        let (calls, launches) = calls;
        let on_device_thread = if calls.0 > 0.0 {
            format!(
                "; {:.1} ms a step in {:.0} calls on cubecl's device thread (each waits for it to catch up), \
                 which spent {:.1} ms a step launching {:.0} kernels",
                1e3 * calls.1,
                calls.0,
                1e3 * launches.1,
                launches.0
            )
        } else {
            String::new()
        };
        writeln!(
            out,
            "host          forward {:.1} ms, backward {:.1} ms, all-reduce {:.1} ms, optimizer {:.1} ms, \
             then waits {:.1} ms for the device (time to queue each phase; medians){on_device_thread}",
            1e3 * f,
            1e3 * b,
            1e3 * r,
            1e3 * o,
            1e3 * w,
        )?;
    }
    if let [Some(f), Some(b), Some(r), Some(o)] = phases {
        writeln!(
            out,
            "phases        forward {:.1} ms, backward {:.1} ms, all-reduce {:.1} ms, optimizer {:.1} ms \
             (synced after each; medians)",
            1e3 * f,
            1e3 * b,
            1e3 * r,
            1e3 * o
        )?;
    }
    writeln!(
        out,
        "throughput    {:.0} tokens/s ({:.0} per rank)",
        tokens_per_step / median,
        tokens_per_step / median / world as f64
    )?;
    // MFU is against a GPU's tensor-core peak (`--peak-tflops`); a CPU has no such figure here.
    let mfu = if cuda {
        format!(
            ", MFU {:.1}% of {} TFLOP/s per device",
            100.0 * flops / median / (a.peak_tflops * 1e12 * world as f64),
            a.peak_tflops
        )
    } else {
        String::new()
    };
    writeln!(
        out,
        "compute       {:.2} TFLOP/step, {:.1} TFLOP/s{mfu}",
        flops / 1e12,
        flops / median / 1e12,
    )?;
    let (peak, live, lives, peaks) = peak;
    if peak > 0 {
        let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
        let ranks = match lives.len() {
            0 | 1 => String::new(),
            _ => format!(
                "; live by rank: {} GiB",
                lives
                    .iter()
                    .map(|g| format!("{g:.2}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let pool = crate::memory_pool::applied().map_or(String::new(), |l| format!(", pool {l}"));
        writeln!(
            out,
            "peak memory   {:.2} GiB reserved, {:.2} GiB live after the forward pass (first and synced steps){ranks}{pool}",
            gib(peak),
            gib(live)
        )?;
        if let Some(top) = peaks.iter().copied().max().filter(|&p| p > 0) {
            let [f, b, g, o] = peaks.map(gib);
            writeln!(
                out,
                "live at peak  {:.2} GiB (forward {f:.2}, backward {b:.2}, gradients {g:.2}, optimizer {o:.2}; \
                 step {}, read at every allocation)",
                gib(top),
                a.warmup
            )?;
        }
    } else {
        writeln!(out, "peak memory   not measured on this device")?;
    }
    Ok(())
}
