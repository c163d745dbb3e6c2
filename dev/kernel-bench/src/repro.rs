//! `umgen-kernel-bench repro`: one training run repeated in one process, its read-outs compared step by step.
//!
//! Every step of a run is a function of the seed (`umgen_train::train`), so runs of one binary on one
//! device should agree bit for bit unless a kernel sums in a varying order (atomics) or reads memory
//! before it is written (a race between streams). Repeating the run inside one process compiles the
//! kernels once (27 s of a `small-bundled` run's first step on an H100) and keeps everything else equal.

use crate::args::BenchReproArgs;
use anyhow::{Context, bail, ensure};
use burn::tensor::backend::AutodiffBackend;
use safetensors::{Dtype, SafeTensors};
use std::io::Write;
use std::ops::ControlFlow;
use umgen::UmgenConfig;
use umgen::checkpoint::load;
use umgen::dist::DistEnv;
use umgen::train::{RunSpec, train};
use umgen_cli::device::Device;

/// What one run read out: each logged step's values, and the final weights.
struct Trace {
    steps: Vec<(u64, Vec<(String, f64)>)>,
    weights: Vec<u8>,
}

/// Trains the config `runs` times from its seed and compares the runs with the first.
pub fn run(a: &BenchReproArgs) -> anyhow::Result<()> {
    ensure!(a.runs >= 2, "--runs {}: compare two or more runs", a.runs);
    ensure!(a.steps >= 1, "--steps 0: no step to compare");
    ensure!(
        a.log_every >= 1,
        "--log-every 0: give the steps between read-outs"
    );
    ensure!(
        a.tolerance.is_finite() && a.tolerance >= 0.0,
        "--tolerance {}: give a relative difference of 0 or more",
        a.tolerance
    );
    let env = DistEnv::from_env()?;
    ensure!(
        env.world_size == 1,
        "umgen-kernel-bench repro compares runs of one process, but this is rank {} of {}: start it without `umgen launch`",
        env.rank,
        env.world_size
    );
    let scratch = tempfile::tempdir().context("a scratch directory for the runs")?;
    let mut sets = a.config.set.clone();
    sets.extend([
        format!("train.steps={}", a.steps),
        format!("train.log_every={}", a.log_every),
        format!("train.checkpoint_every={}", a.steps),
        "train.keep_checkpoints=1".into(),
    ]);
    let config = UmgenConfig::load(&a.config.config, &sets)?;
    let device = Device::parse(&a.device)?;
    let (mut run, tokens) =
        umgen_cli::commands::train::prepare(&config, device, &env, &umgen_cli::Kinds::default())?;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "{} runs of {} steps from seed {} on {}, read out every {} step(s)",
        a.runs, a.steps, run.train.seed, a.device, a.log_every
    )?;
    // Only the first run is kept: every later one is compared with it and dropped (a trace holds the weights).
    let mut first: Option<Trace> = None;
    let mut differing = 0;
    for i in 0..a.runs {
        run.train.out_dir = scratch.path().join(format!("run-{i}"));
        let trace = umgen_cli::with_autodiff!(device, |B, dev| { once::<B>(&run, &tokens, &dev) })
            .with_context(|| format!("run {i}"))?;
        let last = trace.steps.last().map_or(f64::NAN, |(_, v)| v[0].1);
        let verdict = match &first {
            None => {
                first = Some(trace);
                "the reference".to_string()
            }
            Some(reference) => {
                let (words, agrees) = compare(reference, &trace, a.tolerance)?;
                differing += usize::from(!agrees);
                words
            }
        };
        writeln!(out, "run {i}: loss {last:.6} at step {}; {verdict}", a.steps)?;
    }
    #[cfg(feature = "cuda")]
    if umgen::ops::foreign_streams() > 0 {
        writeln!(
            out,
            "side-stream work met another cubecl stream {} time(s)",
            umgen::ops::foreign_streams()
        )?;
    }
    if differing > 0 {
        bail!(
            "{differing} of {} runs left the first run's read-outs or weights (tolerance {})",
            a.runs - 1,
            a.tolerance
        );
    }
    Ok(())
}

/// One run of `run` on `device`, its scratch directory removed afterwards.
fn once<B: AutodiffBackend>(
    run: &RunSpec,
    tokens: &umgen::data::TokenSet,
    device: &B::Device,
) -> anyhow::Result<Trace> {
    let mut steps = Vec::new();
    let mut group = umgen::dist::Single;
    let summary = train::<B>(run, tokens, device, false, &mut group, |r| {
        if let Some(v) = &r.values {
            // The rate differs from run to run by nature.
            let kept = v.iter().filter(|(k, _)| k != "tokens_per_s").cloned().collect();
            steps.push((r.step, kept));
        }
        ControlFlow::Continue(())
    })?;
    let dir = summary
        .checkpoint
        .with_context(|| format!("{} holds no final checkpoint", run.train.out_dir.display()))?;
    let weights = load(&dir)?.file("model.safetensors")?.to_vec();
    std::fs::remove_dir_all(&run.train.out_dir)
        .with_context(|| format!("removing {}", run.train.out_dir.display()))?;
    Ok(Trace { steps, weights })
}

/// `|a - b| / |b|`, 0 where both are equal (NaN included) and infinite where only `b` is 0.
fn relative(a: f64, b: f64) -> f64 {
    if a == b || (a.is_nan() && b.is_nan()) {
        0.0
    } else if b == 0.0 || !a.is_finite() || !b.is_finite() {
        f64::INFINITY
    } else {
        ((a - b) / b).abs()
    }
}

/// `run` against `first` in words, and whether it agrees within `tolerance`: the first read-out that
/// differs (step and value), and the weights' largest difference.
fn compare(first: &Trace, run: &Trace, tolerance: f64) -> anyhow::Result<(String, bool)> {
    let mut words = Vec::new();
    let mut agrees = true;
    let left = first
        .steps
        .iter()
        .zip(&run.steps)
        .find_map(|((step, a), (_, b))| {
            a.iter()
                .zip(b)
                .map(|((key, x), (_, y))| (key, *x, *y, relative(*y, *x)))
                .filter(|(.., d)| *d > tolerance)
                .max_by(|p, q| p.3.total_cmp(&q.3))
                .map(|(key, x, y, d)| {
                    format!("left it at step {step}: {key} {y:.6} against {x:.6} ({d:.1e})")
                })
        });
    match left {
        Some(w) => {
            agrees = false;
            words.push(w);
        }
        None => words.push("read-outs agree".into()),
    }
    let differences = weights_difference(&first.weights, &run.weights, tolerance)?;
    let worst = differences.iter().map(|d| d.most).fold(0.0, f64::max);
    let over: Vec<String> = differences
        .iter()
        .filter(|d| d.most > tolerance)
        .map(|d| format!("{} {:.1e} in {:.0} %", d.name, d.most, 100.0 * d.share))
        .collect();
    if !over.is_empty() {
        agrees = false;
        // The tensors that differ place the fault when the runs are short: after one step without gradient
        // clipping, AdamW moves every weight by about ±lr, so the values that differ are those whose
        // gradient changed sign, and a tensor with many of them is near the wrong computation.
        let shown = over
            .iter()
            .take(MAX_NAMED)
            .cloned()
            .collect::<Vec<_>>()
            .join(", ");
        let more = over.len().saturating_sub(MAX_NAMED);
        let rest = if more > 0 {
            format!(" and {more} more")
        } else {
            String::new()
        };
        words.push(format!(
            "weights differ in {} of {} tensors: {shown}{rest}",
            over.len(),
            differences.len()
        ));
    } else {
        words.push(if worst == 0.0 {
            "weights identical".into()
        } else {
            format!("weights within {worst:.1e}")
        });
    }
    Ok((words.join("; "), agrees))
}

/// Tensors named when weights differ.
const MAX_NAMED: usize = 8;

/// How one tensor of a later run differs from the first run's.
struct Difference {
    name: String,
    /// The largest difference relative to the first run's largest magnitude (infinite where the dtype or
    /// shape differ, or the first run's tensor is all zeros).
    most: f64,
    /// The share of values that differ by more than the tolerance.
    share: f64,
}

/// Every tensor of two weight files compared, the largest share of differing values first (then the
/// largest difference).
fn weights_difference(first: &[u8], other: &[u8], tolerance: f64) -> anyhow::Result<Vec<Difference>> {
    let (a, b) = (
        SafeTensors::deserialize(first).context("the first run's weights")?,
        SafeTensors::deserialize(other).context("a later run's weights")?,
    );
    let floats = |d: &[u8]| -> Vec<f32> {
        d.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    };
    let mut all = Vec::new();
    for (name, x) in a.tensors() {
        let y = b
            .tensor(&name)
            .with_context(|| format!("tensor {name} of the later run"))?;
        if x.dtype() != Dtype::F32 || y.dtype() != Dtype::F32 || x.shape() != y.shape() {
            let same = x.data() == y.data() && x.shape() == y.shape();
            let (most, share) = if same { (0.0, 0.0) } else { (f64::INFINITY, 1.0) };
            all.push(Difference { name, most, share });
            continue;
        }
        let (xs, ys) = (floats(x.data()), floats(y.data()));
        let scale = xs.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
        let each: Vec<f64> = xs
            .iter()
            .zip(&ys)
            .map(
                |(p, q)| match (p == q || (p.is_nan() && q.is_nan()), scale > 0.0) {
                    (true, _) => 0.0,
                    (false, true) => (*q as f64 - *p as f64).abs() / scale,
                    (false, false) => f64::INFINITY,
                },
            )
            .collect();
        let most = each.iter().copied().fold(0.0f64, f64::max);
        let share = each.iter().filter(|d| **d > tolerance).count() as f64 / each.len().max(1) as f64;
        all.push(Difference { name, most, share });
    }
    all.sort_by(|p, q| {
        q.share
            .total_cmp(&p.share)
            .then_with(|| q.most.total_cmp(&p.most))
            .then_with(|| p.name.cmp(&q.name))
    });
    Ok(all)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use safetensors::tensor::TensorView;

    fn weights(values: &[f32]) -> Vec<u8> {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = TensorView::new(Dtype::F32, vec![values.len()], &bytes).unwrap();
        safetensors::serialize([("w", view)], None).unwrap()
    }

    fn trace(losses: &[f64], w: &[f32]) -> Trace {
        Trace {
            steps: losses
                .iter()
                .enumerate()
                .map(|(i, l)| (i as u64 + 1, vec![("loss".into(), *l), ("grad_norm".into(), 1.0)]))
                .collect(),
            weights: weights(w),
        }
    }

    #[test]
    fn the_first_differing_step_and_the_weights_are_named() {
        let first = trace(&[3.0, 2.0, 1.5], &[1.0, -2.0]);
        let (words, agrees) = compare(&first, &trace(&[3.0, 2.0, 1.5], &[1.0, -2.0]), 0.0).unwrap();
        assert!(agrees);
        assert_eq!(words, "read-outs agree; weights identical");
        let (words, agrees) = compare(&first, &trace(&[3.0, 2.2, 1.6], &[1.0, -2.5]), 0.0).unwrap();
        assert!(!agrees);
        // Step 2 is the first to differ, by 0.2 / 2.0; the weights by 0.5 against a largest magnitude of 2.
        assert!(
            words.starts_with("left it at step 2: loss 2.200000 against 2.000000 (1.0e-1)"),
            "{words}"
        );
        assert!(
            words.ends_with("weights differ in 1 of 1 tensors: w 2.5e-1 in 50 %"),
            "{words}"
        );
        // Within a tolerance the same runs agree.
        let (words, agrees) = compare(&first, &trace(&[3.0, 2.2, 1.6], &[1.0, -2.5]), 0.3).unwrap();
        assert!(agrees, "{words}");
        assert!(words.ends_with("weights within 2.5e-1"), "{words}");
    }

    fn named(tensors: &[(&str, &[f32])]) -> Vec<u8> {
        let bytes: Vec<(String, Vec<u8>, usize)> = tensors
            .iter()
            .map(|(n, v)| {
                (
                    n.to_string(),
                    v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                    v.len(),
                )
            })
            .collect();
        let views = bytes
            .iter()
            .map(|(n, b, len)| (n.clone(), TensorView::new(Dtype::F32, vec![*len], b).unwrap()));
        safetensors::serialize(views, None).unwrap()
    }

    #[test]
    fn tensors_with_more_differing_values_come_first() {
        // `a` differs in one value of four by a lot, `b` in three of four by a little, `c` not at all.
        let first = named(&[("a", &[1.0; 4]), ("b", &[1.0; 4]), ("c", &[1.0; 4])]);
        let later = named(&[
            ("a", &[1.0, 1.0, 1.0, 3.0]),
            ("b", &[1.1, 1.1, 1.1, 1.0]),
            ("c", &[1.0; 4]),
        ]);
        let d = weights_difference(&first, &later, 0.0).unwrap();
        let order: Vec<(&str, f64)> = d.iter().map(|d| (d.name.as_str(), d.share)).collect();
        assert_eq!(order, [("b", 0.75), ("a", 0.25), ("c", 0.0)]);
        assert!((d[1].most - 2.0).abs() < 1e-6 && (d[0].most - 0.1).abs() < 1e-6);
        // Above the tolerance only `a`'s value counts.
        let d = weights_difference(&first, &later, 0.5).unwrap();
        assert_eq!(d[0].name, "a");
        assert_eq!(d[0].share, 0.25);
        assert_eq!(d[1].share, 0.0);
    }

    #[test]
    fn nan_counts_as_equal_only_to_nan() {
        assert_eq!(relative(f64::NAN, f64::NAN), 0.0);
        assert_eq!(relative(f64::NAN, 1.0), f64::INFINITY);
        assert_eq!(relative(1.0, 0.0), f64::INFINITY);
        assert!((relative(1.1, 1.0) - 0.1).abs() < 1e-12);
    }
}
