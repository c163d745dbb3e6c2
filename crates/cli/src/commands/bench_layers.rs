//! `umgen bench layers`: the layer norm, the attention over time and the cross-entropy as training runs
//! them (on CUDA, the kernels of `umgen_backbone::norm`, `umgen_backbone::temporal` and
//! `umgen_backbone::xent`) against burn's own operations on the same device: agreement of outputs and
//! gradients, and forward+backward time.

use super::bench_attention::rel_err;
use crate::cli::BenchLayersArgs;
use crate::device::Device;
use anyhow::Context;
use burn::nn::{LayerNorm, LayerNormConfig};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::module::attention_fallback;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Distribution, Int, Tensor};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Precision;
use umgen::backbone::norm::layer_norm;
use umgen::backbone::temporal::{from_heads, over_time_for, to_heads};

/// Measures.
pub fn run(a: &BenchLayersArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.iters > 0, "--iters must be at least 1");
    let [b, t, n, d] = a.shape[..] else {
        anyhow::bail!("--shape takes four sizes B,T,N,D, got {:?}", a.shape);
    };
    anyhow::ensure!(a.vocab > 0, "--vocab must be at least 1");
    anyhow::ensure!(
        b * t * n * d > 0 && a.heads > 0 && d % a.heads == 0,
        "--shape {:?} with --heads {}: positive sizes, D a multiple of the heads",
        a.shape,
        a.heads
    );
    let device = Device::parse(&a.device)?;
    crate::with_autodiff!(device, |B, dev| { measure::<B>(a, [b, t, n, d], &dev) })
}

/// The median forward+backward seconds of `pass` over `iters` runs (after one untimed), and its last
/// result: the output and the gradients it returns.
fn timed<B: AutodiffBackend, const K: usize>(
    iters: usize,
    dev: &B::Device,
    pass: impl Fn() -> anyhow::Result<[Tensor<B::InnerBackend, 4>; K]>,
) -> anyhow::Result<(f64, [Tensor<B::InnerBackend, 4>; K])> {
    let mut times = Vec::new();
    let mut last = None;
    for i in 0..=iters {
        let t0 = Instant::now();
        let result = pass()?;
        B::sync(dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"))?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64());
        }
        last = Some(result);
    }
    times.sort_by(f64::total_cmp);
    Ok((times[times.len() / 2], last.context("no pass ran")?))
}

fn measure<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    [b, t, n, d]: [usize; 4],
    dev: &B::Device,
) -> anyhow::Result<()> {
    B::seed(dev, 7);
    let normal = Distribution::Normal(0.0, 1.0);
    let inner = |dims: [usize; 4]| Tensor::<B::InnerBackend, 4>::random(dims, normal, dev);
    let (x, w) = (inner([b, t, n, d]), inner([b, t, n, d]));
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "layers of [{b}, {t}, {n}, {d}] on {}, forward + backward, median of {} passes; err = max|Δ| / \
         max|burn's|",
        a.device, a.iters
    )?;
    writeln!(
        out,
        "{:<26} {:>9} {:>9} {:>9} {:>9} {:>9}",
        "layer", "ms", "burn ms", "err y", "err dx", "err dp"
    )?;

    // The layer norm: output, input gradient, scale gradient (as a [1, 1, 1, d] tensor).
    let mut ln: LayerNorm<B> = LayerNormConfig::new(d).init(dev);
    ln.gamma = burn::module::Param::from_tensor(Tensor::random([d], Distribution::Normal(1.0, 0.3), dev));
    let norm_pass = |ours: bool| {
        let xa = Tensor::<B, 4>::from_inner(x.clone()).require_grad();
        let y = if ours {
            layer_norm(&ln, xa.clone())
        } else {
            ln.forward(xa.clone())
        };
        let g = (y.clone() * Tensor::from_inner(w.clone())).sum().backward();
        let dx = xa.grad(&g).context("no input gradient")?;
        let dgamma = ln.gamma.val().grad(&g).context("no scale gradient")?;
        Ok([y.inner(), dx, dgamma.reshape([1, 1, 1, d])])
    };
    let (ms, [y, dx, dg]) = timed::<B, 3>(a.iters, dev, || norm_pass(true))?;
    let (burn_ms, [ry, rdx, rdg]) = timed::<B, 3>(a.iters, dev, || norm_pass(false))?;
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9.1e} {:>9.1e}",
        "layer norm",
        ms * 1e3,
        burn_ms * 1e3,
        rel_err(y, ry),
        rel_err(dx, rdx),
        rel_err(dg, rdg)
    )?;

    // Attention over time: output, query gradient, key/value gradient.
    let op = over_time_for::<B>().context("no attention over time on this backend")?;
    let kv = inner([b, t, n, 2 * d]);
    let heads = a.heads;
    let temporal_pass = |ours: bool| {
        let qa = Tensor::<B, 4>::from_inner(x.clone()).require_grad();
        let kva = Tensor::<B, 4>::from_inner(kv.clone()).require_grad();
        let y = if ours {
            op(qa.clone(), kva.clone(), heads, true, Precision::F32)
        } else {
            let h = |x| to_heads(x, heads);
            let (k, v) = (kva.clone().narrow(3, 0, d), kva.clone().narrow(3, d, d));
            let opts = AttentionModuleOptions {
                is_causal: true,
                ..Default::default()
            };
            from_heads(
                attention_fallback(h(qa.clone()), h(k), h(v), None, None, opts),
                b,
                n,
            )
        };
        let g = (y.clone() * Tensor::from_inner(w.clone())).sum().backward();
        let dq = qa.grad(&g).context("no query gradient")?;
        let dkv = kva.grad(&g).context("no key/value gradient")?;
        Ok([y.inner(), dq, dkv])
    };
    let (ms, [y, dq, dkv]) = timed::<B, 3>(a.iters, dev, || temporal_pass(true))?;
    let (burn_ms, [ry, rdq, rdkv]) = timed::<B, 3>(a.iters, dev, || temporal_pass(false))?;
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9.1e} {:>9.1e}",
        format!("attention over time, {heads}h"),
        ms * 1e3,
        burn_ms * 1e3,
        rel_err(y, ry),
        rel_err(dq, rdq),
        rel_err(dkv, rdkv)
    )?;
    cross_entropy::<B>(a, t * n, dev, &mut out)?;
    writeln!(
        out,
        "(err dp: the scale's gradient for the norm, the keys' and values' for the attention; err y of the \
         cross-entropy: its summed loss; fallbacks: {} norm pass(es), {} attention pass(es), {} \
         cross-entropy pass(es))",
        umgen::backbone::norm::fallbacks(),
        umgen::backbone::flash::fallbacks(),
        umgen::backbone::xent::fallbacks()
    )?;
    Ok(())
}

/// The cross-entropy of `rows` random logits `[rows, --vocab]` against random targets smoothed over
/// neighbouring ids (σ 1.5, every id ordered): loss and logit gradient, with the kernels chosen and
/// with burn's operations (the same custom operation with `train.xent = "burn"`).
fn cross_entropy<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    rows: usize,
    dev: &B::Device,
    out: &mut impl Write,
) -> anyhow::Result<()> {
    use umgen::backbone::xent::{self, XentKernel};
    let v = a.vocab;
    let logits = Tensor::<B::InnerBackend, 2>::random([rows, v], Distribution::Normal(0.0, 2.0), dev);
    let targets = Tensor::<B, 2, Int>::random([rows, 1], Distribution::Uniform(0.0, v as f64), dev);
    let pass = |kernel: XentKernel| {
        xent::select(kernel);
        let xa = Tensor::<B, 2>::from_inner(logits.clone()).require_grad();
        let loss = xent::sum(xa.clone(), targets.clone(), v, 1.5);
        let g = loss.clone().backward();
        let dx = xa.grad(&g).context("no logit gradient")?;
        Ok([loss.inner().reshape([1, 1, 1, 1]), dx.reshape([1, 1, rows, v])])
    };
    let chosen = xent::selected();
    let ran = timed::<B, 2>(a.iters, dev, || pass(XentKernel::Fused))
        .and_then(|ours| Ok((ours, timed::<B, 2>(a.iters, dev, || pass(XentKernel::Burn))?)));
    xent::select(chosen);
    let ((ms, [y, dx]), (burn_ms, [ry, rdx])) = ran?;
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9.1e} {:>9}",
        format!("cross-entropy, {v} ids"),
        ms * 1e3,
        burn_ms * 1e3,
        rel_err(y, ry),
        rel_err(dx, rdx),
        "-"
    )?;
    Ok(())
}
