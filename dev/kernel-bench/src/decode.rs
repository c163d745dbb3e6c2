//! `umgen-kernel-bench decode`: the parts of one decoding step timed one by one, so that a slow
//! step can be traced to its part (the OAR layers, the head over a large vocabulary, the device draw and
//! its top-k, or a read-back to the host) without a profiler on the GPU machine.

use crate::args::DecodeArgs;
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Int, Tensor};
use rand::{SeedableRng, rngs::StdRng};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Backbone;
use umgen::generate::{DeviceTopK, Sampling};
use umgen::{backbone_spec, builtin_catalog};
use umgen_cli::commands::bench::bench_config;
use umgen_cli::device::Device;

/// One timed part: its name and milliseconds per step.
pub struct Part {
    /// What was timed.
    pub name: String,
    /// Milliseconds per step (median of three runs of `steps` steps).
    pub ms: f64,
}

/// Times `steps` repetitions of `f` (after one untimed call) three times, waiting for the device at the
/// end of each run; milliseconds per repetition, the median run.
fn time<I: Backend>(
    dev: &I::Device,
    steps: usize,
    mut f: impl FnMut(usize) -> anyhow::Result<()>,
) -> anyhow::Result<f64> {
    let sync = || I::sync(dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"));
    f(0)?;
    sync()?;
    let mut runs = Vec::new();
    for _ in 0..3 {
        let t0 = Instant::now();
        for i in 0..steps {
            f(i)?;
        }
        sync()?;
        runs.push(1e3 * t0.elapsed().as_secs_f64() / steps as f64);
    }
    runs.sort_by(f64::total_cmp);
    Ok(runs[1])
}

/// The parts of a decoding step of `m` scenes for the segment with the largest vocabulary, drawn with
/// `sampling` (device draws with both top-k methods where `reduce_top_k`, i.e. on CUDA), and whether the
/// two methods found the same top-k ids on random logits (`None` when only one ran).
pub fn breakdown<I: Backend>(
    model: &Backbone<I>,
    m: usize,
    sampling: Sampling,
    reduce_top_k: bool,
    dev: &I::Device,
) -> anyhow::Result<(Vec<Part>, Option<bool>)> {
    let spec = model.spec();
    let (seg, vocab) = spec
        .segments
        .iter()
        .enumerate()
        .map(|(i, s)| (i, s.vocab))
        .max_by_key(|&(_, v)| v)
        .ok_or_else(|| anyhow::anyhow!("the layout has no segments"))?;
    let label = &spec.segments[seg].label;
    let d = model.embed_width();
    // One frame's cache holds N positions: the step runs over the first `steps` of them.
    let steps = spec.n.min(256);
    let h = Tensor::<I, 2>::random([m, d], Distribution::Normal(0.0, 1.0), dev);
    let prev = Tensor::<I, 1, Int>::zeros([m], dev);
    let mut parts = Vec::new();
    let mut part = |name: String, ms: f64| {
        tracing::info!("breakdown: {name} {ms:.3} ms/step");
        parts.push(Part { name, ms });
    };
    part(
        "OAR input (embedding + prior)".into(),
        time::<I>(dev, steps, |p| {
            let _ = model.oar_input_at(p + 1, Some(prev.clone()), h.clone());
            Ok(())
        })?,
    );
    let mut cache = model.oar_cache();
    let ms = time::<I>(dev, steps - 1, |p| {
        // The untimed call takes position 0; a run of `steps - 1` fills the rest, then a fresh cache.
        if p == 0 && cache.len() + steps - 1 > cache.capacity() {
            cache = model.oar_cache();
        }
        let w = model.oar_input_at(p + 1, Some(prev.clone()), h.clone());
        model.oar_step(w, &mut cache)?;
        Ok(())
    })?;
    part("OAR input + layers (one position)".into(), ms);
    let x = Tensor::<I, 2>::random([m, d], Distribution::Normal(0.0, 1.0), dev);
    part(
        format!("head over `{label}` ({vocab} ids)"),
        time::<I>(dev, steps, |_| {
            let _ = model.logits_at(seg, x.clone(), false);
            Ok(())
        })?,
    );
    let logits = Tensor::<I, 2>::random([m, vocab], Distribution::Normal(0.0, 3.0), dev);
    let width = sampling.draw_width(vocab);
    let u = Tensor::<I, 2>::random([m, width], Distribution::Uniform(0.01, 0.99), dev);
    let mut methods = vec![("rounds", DeviceTopK::Rounds)];
    if reduce_top_k {
        methods.push(("reduce", DeviceTopK::Reduce));
    }
    for (name, method) in &methods {
        part(
            format!("device draw, top-{} by {name}", sampling.top_k),
            time::<I>(dev, steps, |_| {
                let _ = sampling.draw_rows_with(logits.clone(), u.clone(), *method);
                Ok(())
            })?,
        );
    }
    let mut rng = StdRng::seed_from_u64(0);
    part(
        "read-back of the logits + host draw".into(),
        time::<I>(dev, steps, |_| {
            let host: Vec<f32> = logits.clone().into_data().iter::<f32>().collect();
            for row in host.chunks(vocab) {
                sampling.draw(row, &mut rng);
            }
            Ok(())
        })?,
    );
    let agree = if reduce_top_k && sampling.top_k > 0 {
        let k = sampling.top_k.min(vocab);
        let ids = |method: DeviceTopK| -> Vec<i64> {
            method
                .rows(logits.clone(), k)
                .1
                .into_data()
                .iter::<i64>()
                .collect()
        };
        Some(ids(DeviceTopK::Rounds) == ids(DeviceTopK::Reduce))
    } else {
        None
    };
    Ok((parts, agree))
}

/// Builds the config's model with random weights on `--device` and prints the parts of its decoding step.
pub fn run(a: &DecodeArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.batch >= 1, "--batch must be at least 1");
    let (config, path, _) = bench_config(&a.model)?;
    let registry = config.registry(&builtin_catalog()?)?;
    let cfg = config.backbone.for_inference();
    let spec = backbone_spec(&registry, &cfg)?;
    let device = Device::parse(&a.device)?;
    let on_gpu = matches!(device, Device::Cuda(_));
    let (parts, agree) = umgen_cli::with_inference!(device, |I, dev| {
        <I as Backend>::seed(&dev, 0);
        let model = Backbone::<I>::new(&cfg, &spec, &dev)?;
        breakdown(&model, a.batch, Sampling::default(), on_gpu, &dev)?
    });
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "parts of one decoding step ({}, N = {}, batch {}, {}; median of 3 runs, ms/step):",
        path.display(),
        spec.n,
        a.batch,
        a.device
    )?;
    for p in parts {
        writeln!(out, "  {:<48} {:>9.3}", p.name, p.ms)?;
    }
    if let Some(agree) = agree {
        writeln!(
            out,
            "  top-k by reduce and by rounds: {}",
            if agree { "same ids" } else { "DIFFERENT ids" }
        )?;
    }
    Ok(())
}
