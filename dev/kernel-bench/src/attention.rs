//! `umgen-kernel-bench attention`: the training attention's kernels (fused, tiled) against burn's decomposed
//! attention on the device, for correctness (outputs and gradients) and for time and memory.

use crate::args::BenchAttentionArgs;
use anyhow::Context;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::module::attention_fallback;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Distribution, ElementConversion, FloatDType, Tensor};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Precision;
use umgen::ops::Kernels;
use umgen::ops::attention::tiled_for;
use umgen::ops::flash::{self, AttentionKernel};
use umgen::ops::kernels::Flash2Backward;
use umgen_cli::device::{Device, memory_in_use};

/// One measured shape.
#[derive(Debug, Clone, Copy)]
pub(super) struct Case {
    pub(super) seqs: usize,
    pub(super) heads: usize,
    pub(super) lq: usize,
    pub(super) lk: usize,
    pub(super) dh: usize,
    pub(super) causal: bool,
}

impl Case {
    fn parse(s: &str) -> anyhow::Result<Self> {
        let (body, causal) = match s.strip_suffix('c') {
            Some(b) => (b, true),
            None => (s, false),
        };
        let n: Vec<usize> = body
            .split('x')
            .map(|x| x.parse::<usize>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("--cases `{s}`: expected SEQSxHEADSxLQxLKxDH[c]"))?;
        match n[..] {
            [seqs, heads, lq, lk, dh] if n.iter().all(|&x| x > 0) && (!causal || lk >= lq) => Ok(Self {
                seqs,
                heads,
                lq,
                lk,
                dh,
                causal,
            }),
            _ => anyhow::bail!(
                "--cases `{s}`: need five positive sizes SEQSxHEADSxLQxLKxDH (LK ≥ LQ when causal)"
            ),
        }
    }
}

/// Output and q, k, v gradients of one path, and its median forward+backward time.
struct Run<B: Backend> {
    out: Tensor<B, 4>,
    grads: [Tensor<B, 4>; 3],
    seconds: f64,
    reserved: u64,
}

fn measure<B: AutodiffBackend>(
    c: &Case,
    tiled: Option<(Precision, Kernels)>,
    iters: usize,
    device: Device,
    dev: &B::Device,
) -> anyhow::Result<Run<B::InnerBackend>> {
    B::seed(dev, 7);
    let shape = |l: usize| [c.seqs, c.heads, l, c.dh];
    let normal = Distribution::Normal(0.0, 1.0);
    let q = Tensor::<B::InnerBackend, 4>::random(shape(c.lq), normal, dev);
    let k = Tensor::<B::InnerBackend, 4>::random(shape(c.lk), normal, dev);
    let v = Tensor::<B::InnerBackend, 4>::random(shape(c.lk), normal, dev);
    let w = Tensor::<B::InnerBackend, 4>::random(shape(c.lq), normal, dev);
    let mut times = Vec::new();
    let mut last = None;
    for i in 0..iters + 1 {
        let t0 = Instant::now();
        let (qa, ka, va) = (
            Tensor::<B, 4>::from_inner(q.clone()).require_grad(),
            Tensor::<B, 4>::from_inner(k.clone()).require_grad(),
            Tensor::<B, 4>::from_inner(v.clone()).require_grad(),
        );
        let y = if let Some((precision, kernels)) = tiled {
            let f = tiled_for::<B>().context("no tiled attention for this backend")?;
            f(qa.clone(), ka.clone(), va.clone(), c.causal, precision, &kernels)
        } else {
            let opts = AttentionModuleOptions {
                is_causal: c.causal,
                ..Default::default()
            };
            attention_fallback(qa.clone(), ka.clone(), va.clone(), None, None, opts)
        };
        // flash2 writes bf16 results from bf16 operands (and gradients): compared in f32.
        let y = y.cast(FloatDType::F32);
        let g = (y.clone() * Tensor::from_inner(w.clone())).sum().backward();
        let grads = [qa.grad(&g), ka.grad(&g), va.grad(&g)].map(|t| t.map(|t| t.cast(FloatDType::F32)));
        let [Some(dq), Some(dk), Some(dv)] = grads else {
            anyhow::bail!("attention gave no gradient to q, k or v");
        };
        B::sync(dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"))?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64());
        }
        last = Some((y.inner(), [dq, dk, dv]));
    }
    times.sort_by(f64::total_cmp);
    let (out, grads) = last.context("no iteration ran")?;
    Ok(Run {
        out,
        grads,
        seconds: times[times.len() / 2],
        reserved: memory_in_use(device),
    })
}

/// max |a − b| / max |b| (also `bench matmul`'s agreement measure).
pub(super) fn rel_err<B: Backend, const D: usize>(a: Tensor<B, D>, b: Tensor<B, D>) -> f64 {
    let scale: f64 = b.clone().abs().max().into_scalar().elem();
    let diff: f64 = (a - b).abs().max().into_scalar().elem();
    diff / scale.max(f64::MIN_POSITIVE)
}

/// One row to measure: the kernel, the tiled one's block size (bytes) or the fused one's loop step (`None`:
/// the default), and flash2's backward pass.
type Variant = (AttentionKernel, Option<usize>, Flash2Backward);

/// The rows to measure: each kernel of `--kernels`, the tiled one once per block size, the fused one once
/// per loop step and flash2 once per `--backward` choice.
fn variants(a: &BenchAttentionArgs, device: Device) -> anyhow::Result<Vec<Variant>> {
    anyhow::ensure!(
        a.block_mib.iter().all(|&m| m > 0),
        "--block-mib sizes must be positive"
    );
    let cuda = !matches!(device, Device::Cpu);
    let kernels: Vec<AttentionKernel> = match a.kernels.is_empty() {
        true if cuda => vec![
            AttentionKernel::Flash2,
            AttentionKernel::Fused,
            AttentionKernel::Tiled,
        ],
        true => vec![AttentionKernel::Tiled],
        false => a.kernels.iter().map(|&k| k.into()).collect(),
    };
    anyhow::ensure!(
        cuda || kernels.iter().all(|&k| k == AttentionKernel::Tiled),
        "--kernels fused and flash2 are CUDA's; on {} only `tiled` runs",
        a.device
    );
    let blocks: Vec<Option<usize>> = match a.block_mib.is_empty() {
        true => vec![None],
        false => a.block_mib.iter().map(|&m| Some(m << 20)).collect(),
    };
    for &s in &a.step {
        flash::check_step(s).map_err(|e| anyhow::anyhow!("--step: {e}"))?;
    }
    let steps: Vec<Option<usize>> = match a.step.is_empty() {
        true => vec![None],
        false => a.step.iter().map(|&s| Some(s)).collect(),
    };
    let backward: Vec<Flash2Backward> = match a.backward.is_empty() {
        true => vec![Flash2Backward::TwoPass, Flash2Backward::OnePass],
        false => a.backward.iter().map(|&b| b.into()).collect(),
    };
    let two = Flash2Backward::TwoPass;
    Ok(kernels
        .into_iter()
        .flat_map(|k| match k {
            AttentionKernel::Fused => steps.iter().map(|&s| (k, s, two)).collect::<Vec<_>>(),
            AttentionKernel::Tiled => blocks.iter().map(|&b| (k, b, two)).collect(),
            AttentionKernel::Flash2 => backward.iter().map(|&b| (k, None, b)).collect(),
        })
        .collect())
}

/// Measures.
pub fn run(a: &BenchAttentionArgs) -> anyhow::Result<()> {
    let cases: Vec<Case> = a.cases.iter().map(|s| Case::parse(s)).collect::<Result<_, _>>()?;
    let device = Device::parse(&a.device)?;
    if a.flash {
        return crate::flash::run(a, &cases, device);
    }
    let variants = variants(a, device)?;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "attention forward+backward on {}, training kernels' products in {}, decomposed in f32; err = \
         max|Δ| / max|decomposed|; GiB = memory pool after the path (the pool only grows: the decomposed \
         figure includes the training kernels')",
        a.device,
        a.precision.name()
    )?;
    writeln!(
        out,
        "{:<22} {:>7} {:>9} {:>10} {:>10} {:>9} {:>9} {:>9} {:>9} {:>11} {:>11}",
        "case",
        "kernel",
        "block",
        "train ms",
        "decomp ms",
        "err out",
        "err dq",
        "err dk",
        "err dv",
        "train GiB",
        "decomp GiB"
    )?;
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    for (c, name) in cases.iter().zip(&a.cases) {
        let rows = umgen_cli::with_autodiff!(device, |B, dev| {
            // Training kernels first: the pool only grows, so the decomposed path's figure includes what
            // they added.
            let mut runs = Vec::new();
            for &(kernel, size, backward) in &variants {
                let mut kernels = Kernels {
                    attention: kernel,
                    attention_backward: backward,
                    ..Kernels::DEFAULT
                };
                match (kernel, size) {
                    (AttentionKernel::Fused, Some(step)) => kernels.attention_step = step,
                    (AttentionKernel::Tiled, Some(bytes)) => kernels.attention_block_mib = bytes >> 20,
                    _ => {}
                }
                runs.push(measure::<B>(
                    c,
                    Some((a.precision.into(), kernels)),
                    a.iters,
                    device,
                    &dev,
                ));
            }
            let d = measure::<B>(c, None, a.iters, device, &dev)?;
            let mut rows = Vec::new();
            for (t, &(kernel, size, backward)) in runs.into_iter().zip(&variants) {
                let t = t?;
                let [tq, tk, tv] = t.grads;
                let [dq, dk, dv] = d.grads.clone();
                let errs = [
                    rel_err(t.out, d.out.clone()),
                    rel_err(tq, dq),
                    rel_err(tk, dk),
                    rel_err(tv, dv),
                ];
                let block = match kernel {
                    AttentionKernel::Fused => format!("step {}", size.unwrap_or(flash::DEFAULT_STEP)),
                    AttentionKernel::Flash2 => match backward {
                        Flash2Backward::TwoPass => "two-pass".into(),
                        Flash2Backward::OnePass => "one-pass".into(),
                    },
                    AttentionKernel::Tiled => {
                        (size.unwrap_or(umgen::ops::kernels::BLOCK_BYTES) >> 20).to_string()
                    }
                };
                rows.push((kernel, block, t.seconds, d.seconds, errs, t.reserved, d.reserved));
            }
            rows
        });
        for (kernel, block, ts, ds, e, tr, dr) in rows {
            let kernel = match kernel {
                AttentionKernel::Fused => "fused",
                AttentionKernel::Tiled => "tiled",
                AttentionKernel::Flash2 => "flash2",
            };
            writeln!(
                out,
                "{name:<22} {kernel:>7} {block:>9} {:>10.2} {:>10.2} {:>9.1e} {:>9.1e} {:>9.1e} {:>9.1e} {:>11.2} {:>11.2}",
                1e3 * ts,
                1e3 * ds,
                e[0],
                e[1],
                e[2],
                e[3],
                gib(tr),
                gib(dr)
            )?;
        }
    }
    if flash::fallbacks() > 0 {
        writeln!(
            out,
            "{} passes fell back from the fused kernels to the tiled ones (see the warning above)",
            flash::fallbacks()
        )?;
    }
    Ok(())
}
