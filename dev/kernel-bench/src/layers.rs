//! `umgen-kernel-bench layers`: the layer norm, the attention over time, an MLP's bias + GELU, the cross-entropy,
//! an embedding table's gradient and an AdamW step as training runs them (on CUDA, the kernels of
//! `umgen_ops::norm`, `umgen_ops::temporal`, `umgen_ops::gelu`, `umgen_ops::xent`,
//! `umgen_ops::lookup` and `umgen_ops::adamw`) against burn's own operations on the same device:
//! agreement of outputs and gradients, and time.

use crate::args::BenchLayersArgs;
use crate::attention::rel_err;
use anyhow::Context;
use burn::nn::{LayerNorm, LayerNormConfig};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::module::attention_fallback;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Distribution, Int, Tensor};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Precision;
use umgen::ops::Kernels;
use umgen::ops::norm::layer_norm;
use umgen::ops::temporal::{from_heads, over_time_for, to_heads};
use umgen_cli::device::Device;

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
    umgen_cli::with_autodiff!(device, |B, dev| { measure::<B>(a, [b, t, n, d], &dev) })
}

/// The median seconds of `pass` over `iters` runs (after one untimed), each waited for on the device, and
/// its last result (for the layers: the output and the gradients it returns).
fn timed<B: AutodiffBackend, T>(
    iters: usize,
    dev: &B::Device,
    pass: impl Fn() -> anyhow::Result<T>,
) -> anyhow::Result<(f64, T)> {
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
    let median = umgen_cli::commands::bench_train::median(times).context("no timed pass (--iters 0)")?;
    Ok((median, last.context("no pass ran")?))
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
            layer_norm(&ln, xa.clone(), &Kernels::DEFAULT)
        } else {
            ln.forward(xa.clone())
        };
        let g = (y.clone() * Tensor::from_inner(w.clone())).sum().backward();
        let dx = xa.grad(&g).context("no input gradient")?;
        let dgamma = ln.gamma.val().grad(&g).context("no scale gradient")?;
        Ok([y.inner(), dx, dgamma.reshape([1, 1, 1, d])])
    };
    let (ms, [y, dx, dg]) = timed::<B, _>(a.iters, dev, || norm_pass(true))?;
    let (burn_ms, [ry, rdx, rdg]) = timed::<B, _>(a.iters, dev, || norm_pass(false))?;
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
            op(
                qa.clone(),
                kva.clone(),
                heads,
                true,
                Precision::F32,
                &Kernels::DEFAULT,
            )
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
    let (ms, [y, dq, dkv]) = timed::<B, _>(a.iters, dev, || temporal_pass(true))?;
    let (burn_ms, [ry, rdq, rdkv]) = timed::<B, _>(a.iters, dev, || temporal_pass(false))?;
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
    mlp_activation::<B>(a, [b * t * n, d], dev, &mut out)?;
    cross_entropy::<B>(a, t * n, dev, &mut out)?;
    table_gradient::<B>(a, [b * t * n, d], dev, &mut out)?;
    adamw::<B>(a, d, dev, &mut out)?;
    writeln!(
        out,
        "(err dp: the scale's gradient for the norm, the keys' and values' for the attention; err y of the \
         cross-entropy: its summed loss; for the MLP's bias + GELU err dp: the bias's gradient, burn's backward \
         pass taking GELU's tanh approximation's derivative; for AdamW err y, dx, dp: the new parameters, first and second \
         moments, and burn ms its arithmetic in burn's operations; err y of the gradient norm: the norm; err dp of the \
         table: its gradient; fallbacks: {} norm pass(es), {} attention pass(es), {} bias + GELU pass(es), {} \
         cross-entropy pass(es), {} table gradient(s), {} AdamW step(s))",
        umgen::ops::norm::fallbacks(),
        umgen::ops::flash::fallbacks(),
        umgen::ops::gelu::fallbacks(),
        umgen::ops::xent::fallbacks(),
        umgen::ops::lookup::fallbacks(),
        umgen::ops::adamw::fallbacks()
    )?;
    Ok(())
}

/// An MLP's first layer, `gelu(x · W + b)` from `d` to `4·d` with bf16 products, as training runs it
/// (`train.kernels.gelu = "fused"`: one operation writing the activation in bf16) and with burn's bias add and GELU
/// (`"burn"`): activation, input gradient and bias gradient.
fn mlp_activation<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    [rows, d]: [usize; 2],
    dev: &B::Device,
    out: &mut impl Write,
) -> anyhow::Result<()> {
    use burn::nn::LinearConfig;
    use burn::tensor::FloatDType;
    use umgen::ops::gelu::{GeluKernel, linear_gelu};
    let layer = LinearConfig::new(d, 4 * d).init::<B>(dev);
    let bias = layer.bias.as_ref().context("an MLP layer has a bias")?.val();
    let x = Tensor::<B::InnerBackend, 2>::random([rows, d], Distribution::Normal(0.0, 1.0), dev);
    let r = Tensor::<B::InnerBackend, 2>::random([rows, 4 * d], Distribution::Normal(0.0, 1.0), dev);
    let pass = |gelu: GeluKernel| {
        let kernels = Kernels {
            gelu,
            ..Kernels::DEFAULT
        };
        let xa = Tensor::<B, 2>::from_inner(x.clone()).require_grad();
        let h = linear_gelu(&layer, xa.clone(), Precision::Bf16, &kernels).cast(FloatDType::F32);
        let g = (h.clone() * Tensor::from_inner(r.clone())).sum().backward();
        let dx = xa.grad(&g).context("no input gradient")?;
        let db = bias.grad(&g).context("no bias gradient")?;
        let as4 = |t: Tensor<B::InnerBackend, 2>| t.unsqueeze::<4>();
        Ok([as4(h.inner()), as4(dx), db.reshape([1, 1, 1, 4 * d])])
    };
    let ran = timed::<B, _>(a.iters, dev, || pass(GeluKernel::Fused))
        .and_then(|ours| Ok((ours, timed::<B, _>(a.iters, dev, || pass(GeluKernel::Burn))?)));
    let ((ms, [y, dx, db]), (burn_ms, [ry, rdx, rdb])) = ran?;
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9.1e} {:>9.1e}",
        format!("MLP bias + GELU, {d}→{}", 4 * d),
        ms * 1e3,
        burn_ms * 1e3,
        rel_err(y, ry),
        rel_err(dx, rdx),
        rel_err(db, rdb)
    )?;
    Ok(())
}

/// The cross-entropy of `rows` random logits `[rows, --vocab]` against random targets smoothed over
/// neighbouring ids (σ 1.5, every id ordered): loss and logit gradient, with the kernels chosen and
/// with burn's operations (the same custom operation with `train.kernels.xent = "burn"`).
fn cross_entropy<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    rows: usize,
    dev: &B::Device,
    out: &mut impl Write,
) -> anyhow::Result<()> {
    use umgen::ops::xent::XentKernel;
    let v = a.vocab;
    let logits = Tensor::<B::InnerBackend, 2>::random([rows, v], Distribution::Normal(0.0, 2.0), dev);
    let targets = Tensor::<B, 2, Int>::random([rows, 1], Distribution::Uniform(0.0, v as f64), dev);
    let pass = |xent: XentKernel| {
        let kernels = Kernels {
            xent,
            ..Kernels::DEFAULT
        };
        let xa = Tensor::<B, 2>::from_inner(logits.clone()).require_grad();
        let loss = umgen::ops::xent::sum(xa.clone(), targets.clone(), v, 1.5, &kernels);
        let g = loss.clone().backward();
        let dx = xa.grad(&g).context("no logit gradient")?;
        Ok([loss.inner().reshape([1, 1, 1, 1]), dx.reshape([1, 1, rows, v])])
    };
    let ran = timed::<B, _>(a.iters, dev, || pass(XentKernel::Fused))
        .and_then(|ours| Ok((ours, timed::<B, _>(a.iters, dev, || pass(XentKernel::Burn))?)));
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

/// The gradient of a `[--vocab, d]` embedding table looked up by `rows` ids, every other one the same id (as
/// a map's empty code): `lookup::embed` (on CUDA a counting sort and sums over the sorted rows) against
/// burn's lookup (`select_assign` into a zero table).
fn table_gradient<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    [rows, d]: [usize; 2],
    dev: &B::Device,
    out: &mut impl Write,
) -> anyhow::Result<()> {
    use burn::nn::EmbeddingConfig;
    use burn::tensor::TensorData;
    use burn::tensor::module::embedding;
    let v = a.vocab;
    let table = EmbeddingConfig::new(v, d).init::<B>(dev);
    let ids: Vec<i64> = (0..rows)
        .map(|i| if i % 2 == 0 { 0 } else { (i * 7_919 % v) as i64 })
        .collect();
    let ids = Tensor::<B, 2, Int>::from_data(TensorData::new(ids, [1, rows]), dev);
    let w = Tensor::<B::InnerBackend, 3>::random([1, rows, d], Distribution::Normal(0.0, 1.0), dev);
    let pass = |ours: bool| {
        let y = if ours {
            umgen::ops::lookup::embed(&table, ids.clone())
        } else {
            embedding(table.weight.val(), ids.clone())
        };
        let g = (y * Tensor::from_inner(w.clone())).sum().backward();
        let dt = table.weight.val().grad(&g).context("no table gradient")?;
        Ok(dt.reshape([1, 1, v, d]))
    };
    let (ms, dt) = timed::<B, _>(a.iters, dev, || pass(true))?;
    let (burn_ms, rdt) = timed::<B, _>(a.iters, dev, || pass(false))?;
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9} {:>9} {:>9.1e}",
        format!("table gradient, {rows} ids"),
        ms * 1e3,
        burn_ms * 1e3,
        "-",
        "-",
        rel_err(dt, rdt)
    )?;
    Ok(())
}

/// One AdamW step over a model's worth of parameter tensors of width `d` (some at their first step, some
/// later, with a clipping factor): the multi-tensor kernel against its arithmetic in burn's operations.
fn adamw<B: AutodiffBackend>(
    a: &BenchLayersArgs,
    d: usize,
    dev: &B::Device,
    out: &mut impl Write,
) -> anyhow::Result<()> {
    use burn::tensor::TensorPrimitive;
    use burn::tensor::ops::FloatTensorOps;
    use umgen::optim::{AdamWSettings, AdamWSlot, AdamWStep, adamw_reference};
    type Raw<B> = burn::tensor::ops::FloatTensor<<B as AutodiffBackend>::InnerBackend>;
    let Some(kernels) = umgen::ops::adamw::kernels::<B::InnerBackend>(&Kernels::DEFAULT) else {
        writeln!(out, "{:<26} no multi-tensor kernel on this backend", "adamw")?;
        return Ok(());
    };
    let raw = |dims: Vec<usize>, dist| -> Raw<B> {
        let n = dims.iter().product::<usize>();
        let flat = Tensor::<B::InnerBackend, 1>::random([n], dist, dev);
        B::InnerBackend::float_reshape(flat.into_primitive().tensor(), burn::tensor::Shape::from(dims))
    };
    // Matrices, biases, an odd length, and 3-D: 40 tensors, so that two launches share them.
    let shapes: Vec<Vec<usize>> = (0..10)
        .flat_map(|i| [vec![d, 4 * d], vec![4 * d], vec![1001 + i], vec![2, d, 3]])
        .collect();
    let normal = Distribution::Normal(0.0, 1.0);
    let slots: Vec<AdamWSlot<B::InnerBackend>> = shapes
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let later = i % 3 != 0;
            let moments = later.then(|| {
                let v = raw(s.clone(), Distribution::Uniform(0.0, 2.0));
                (raw(s.clone(), normal), v)
            });
            AdamWSlot {
                param: raw(s.clone(), normal),
                grad: raw(s.clone(), normal),
                moments,
                time: if later { 7 } else { 1 },
            }
        })
        .collect();
    let scale = Tensor::<B::InnerBackend, 1>::from_floats([0.25], dev);
    let step = AdamWStep {
        settings: AdamWSettings {
            beta_1: 0.9,
            beta_2: 0.95,
            epsilon: 1e-8,
            weight_decay: 0.1,
        },
        lr: 1e-3,
        grad_scale: Some(scale.into_primitive().tensor()),
    };
    let flat = |outs: &[[Raw<B>; 3]], k: usize| {
        let parts: Vec<Tensor<B::InnerBackend, 1>> = outs
            .iter()
            .map(|o| {
                let t = Tensor::<B::InnerBackend, 1>::from_primitive(TensorPrimitive::Float(o[k].clone()));
                let n = t.shape().num_elements();
                t.reshape([n])
            })
            .collect();
        let all = Tensor::cat(parts, 0);
        let n = all.dims()[0];
        all.reshape([1, 1, 1, n])
    };
    let (ms, ours) = timed::<B, _>(a.iters, dev, || {
        (kernels.adamw)(slots.clone(), &step)
            .map_err(|(_, why)| anyhow::anyhow!("the AdamW kernel declined: {why}"))
    })?;
    let (burn_ms, theirs) = timed::<B, _>(a.iters, dev, || Ok(adamw_reference(slots.clone(), &step)))?;
    let errs: Vec<f64> = (0..3)
        .map(|k| rel_err(flat(&ours, k), flat(&theirs, k)))
        .collect();
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9.1e} {:>9.1e}",
        format!("adamw, {} tensors", shapes.len()),
        ms * 1e3,
        burn_ms * 1e3,
        errs[0],
        errs[1],
        errs[2]
    )?;
    // The gradients' global norm, through the kernel and in burn's operations.
    let grads: Vec<Raw<B>> = slots.iter().map(|s| s.grad.clone()).collect();
    let (ms, ours) = timed::<B, _>(a.iters, dev, || {
        let norm =
            (kernels.norm)(&grads).map_err(|why| anyhow::anyhow!("the norm kernel declined: {why}"))?;
        Ok(norm.norm)
    })?;
    let (burn_ms, theirs) = timed::<B, _>(a.iters, dev, || {
        Ok(umgen::optim::norm_reference::<B::InnerBackend>(&grads).norm)
    })?;
    let (ours, theirs) = (ours.reshape([1, 1, 1, 1]), theirs.reshape([1, 1, 1, 1]));
    writeln!(
        out,
        "{:<26} {:>9.3} {:>9.3} {:>9.1e} {:>9} {:>9}",
        format!("gradient norm, {} tensors", shapes.len()),
        ms * 1e3,
        burn_ms * 1e3,
        rel_err(ours, theirs),
        "-",
        "-"
    )?;
    Ok(())
}
