//! `umgen-kernel-bench linear`: a linear layer's product, forward and both gradients, on the kernels training can
//! use (`umgen_ops::matmul`: the named kernel, and cuBLAS on CUDA) against burn's own path on the same
//! backend, and on CUDA cuBLASLt's product with the bias and a residual stream added by its epilogue
//! (`lt+b+r`; `lt16+b` writes bf16 with the bias), both taken off its result again. Each path's output and
//! gradients are compared with burn's f32 path, and each forward+backward pass is timed.

use crate::args::{BenchLinearArgs, PrecisionArg};
use crate::attention::rel_err;
use crate::matmul::Shape;
use anyhow::Context;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{Distribution, FloatDType, Tensor};
use std::io::Write;
use std::time::Instant;
use umgen::backbone::Precision;
use umgen::ops::Kernels;
use umgen::ops::matmul::{MatmulKernel, Written, biased_for, named_for};
use umgen_cli::device::Device;

/// A product under test: `x · w` on the autodiff backend `B`.
type Path<'a, B> = &'a dyn Fn(Tensor<B, 2>, Tensor<B, 2>) -> Tensor<B, 2>;

/// Output, input gradient and weight gradient of one pass, on the inner backend.
type Results<B> = [Tensor<<B as AutodiffBackend>::InnerBackend, 2>; 3];

/// Measures.
pub fn run(a: &BenchLinearArgs) -> anyhow::Result<()> {
    let shapes: Vec<Shape> = a
        .shapes
        .iter()
        .map(|s| Shape::parse(s))
        .collect::<Result<_, _>>()?;
    if let Some((s, _)) = a.shapes.iter().zip(&shapes).find(|(_, s)| s.batch != 1) {
        anyhow::bail!("--shapes `{s}`: a linear layer's product has no batch, give MxKxN");
    }
    anyhow::ensure!(a.iters > 0, "--iters must be at least 1");
    let device = Device::parse(&a.device)?;
    umgen_cli::with_autodiff!(device, |B, dev| { measure::<B>(a, &shapes, &dev) })
}

fn measure<B: AutodiffBackend>(a: &BenchLinearArgs, shapes: &[Shape], dev: &B::Device) -> anyhow::Result<()> {
    let named =
        named_for::<B>(&Kernels::DEFAULT).with_context(|| format!("no named matmul on {}", a.device))?;
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "linear products on {}, forward + backward, median of {} passes; err = max|Δ| / max|burn f32| of \
         y, dx, dw",
        a.device, a.iters
    )?;
    writeln!(
        out,
        "{:<20} {:<5} {:<6} {:>10} {:>9} {:>9} {:>9} {:>9}",
        "shape", "dtype", "path", "ms", "TFLOP/s", "err y", "err dx", "err dw"
    )?;
    for (shape, text) in shapes.iter().zip(&a.shapes) {
        let (m, k, n) = (shape.m, shape.k, shape.n);
        // Unit-variance outputs, as a layer's initialisation gives.
        let x = Tensor::<B::InnerBackend, 2>::random([m, k], Distribution::Normal(0.0, 1.0), dev);
        let w = Tensor::random([k, n], Distribution::Normal(0.0, 1.0 / (k as f64).sqrt()), dev);
        let up = Tensor::random([m, n], Distribution::Normal(0.0, 1.0), dev);
        let bias = Tensor::<B::InnerBackend, 1>::random([n], Distribution::Normal(0.0, 1.0), dev);
        let add = Tensor::<B::InnerBackend, 2>::random([m, n], Distribution::Normal(0.0, 1.0), dev);
        let (reference, _) = pass::<B>(&|x, w| x.matmul(w), &x, &w, &up, 1)?;
        for &dtype in &a.dtypes {
            let p = Precision::from(dtype);
            let burn_path = move |x: Tensor<B, 2>, w: Tensor<B, 2>| match dtype {
                PrecisionArg::F32 => x.matmul(w),
                PrecisionArg::Bf16 => x
                    .cast(FloatDType::BF16)
                    .matmul(w.cast(FloatDType::BF16))
                    .cast(FloatDType::F32),
            };
            let on = |kernel: MatmulKernel, written: Written| {
                let kernels = Kernels {
                    matmul: kernel,
                    ..Kernels::DEFAULT
                };
                move |x: Tensor<B, 2>, w: Tensor<B, 2>| {
                    named(x, w, p, written, &kernels).cast(FloatDType::F32)
                }
            };
            // The result and the input's gradient written in bf16, as the MLP's products write them.
            let half = Written {
                out: FloatDType::BF16,
                dx: FloatDType::BF16,
            };
            let named_path = on(MatmulKernel::Named, Written::F32);
            let cublas_path = on(MatmulKernel::Cublas, Written::F32);
            let cublas_half = on(MatmulKernel::Cublas, half);
            // With the bias and a residual stream added by cuBLASLt's epilogue (`matmul::biased`), taken off
            // again after it so that the result compares with the plain product's.
            let biased = biased_for::<B>(&Kernels::DEFAULT).context("no biased product")?;
            let with_epilogue = |written: Written, residual: bool| {
                let (bias, add) = (bias.clone(), add.clone());
                move |x: Tensor<B, 2>, w: Tensor<B, 2>| {
                    let b = Tensor::<B, 1>::from_inner(bias.clone());
                    let a = residual.then(|| Tensor::<B, 2>::from_inner(add.clone()));
                    let y = biased((x, w, b.clone()), a.clone(), p, written, &Kernels::DEFAULT);
                    let y = y.cast(FloatDType::F32) - b.unsqueeze::<2>();
                    match a {
                        Some(a) => y - a,
                        None => y,
                    }
                }
            };
            let epilogue_path = with_epilogue(Written::F32, true);
            let epilogue_half = with_epilogue(half, false);
            let mut paths: Vec<(&str, Path<B>)> = vec![("burn", &burn_path), ("named", &named_path)];
            // On the CPU every named product is burn's; cuBLAS is a CUDA kernel.
            if a.device.starts_with("cuda") {
                paths.push(("cublas", &cublas_path));
                paths.push(("lt+b+r", &epilogue_path));
                if dtype == PrecisionArg::Bf16 {
                    paths.push(("cub16", &cublas_half));
                    paths.push(("lt16+b", &epilogue_half));
                }
            }
            for (name, path) in paths {
                let (results, secs) = pass::<B>(path, &x, &w, &up, a.iters)?;
                let errs: Vec<String> = results
                    .into_iter()
                    .zip(reference.iter().cloned())
                    .map(|(r, e)| format!("{:.1e}", rel_err(r, e)))
                    .collect();
                writeln!(
                    out,
                    "{text:<20} {:<5} {name:<6} {:>10.3} {:>9.1} {:>9} {:>9} {:>9}",
                    dtype.name(),
                    1e3 * secs,
                    3.0 * shape.flops() / secs / 1e12,
                    errs[0],
                    errs[1],
                    errs[2]
                )?;
                out.flush()?;
            }
        }
    }
    Ok(())
}

/// One untimed pass, then `iters` timed ones: the last pass's results and the median seconds.
fn pass<B: AutodiffBackend>(
    path: Path<B>,
    x: &Tensor<B::InnerBackend, 2>,
    w: &Tensor<B::InnerBackend, 2>,
    up: &Tensor<B::InnerBackend, 2>,
    iters: usize,
) -> anyhow::Result<(Results<B>, f64)> {
    let dev = x.device();
    let mut times = Vec::with_capacity(iters);
    let mut last = None;
    for i in 0..=iters {
        let t0 = Instant::now();
        let xa = Tensor::<B, 2>::from_inner(x.clone()).require_grad();
        let wa = Tensor::<B, 2>::from_inner(w.clone()).require_grad();
        let y = path(xa.clone(), wa.clone());
        let grads = (y.clone() * Tensor::from_inner(up.clone())).sum().backward();
        let dx = xa.grad(&grads).context("no input gradient")?;
        let dw = wa.grad(&grads).context("no weight gradient")?;
        B::sync(&dev).map_err(|e| anyhow::anyhow!("device sync: {e:?}"))?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64());
        }
        last = Some([y.inner(), dx, dw].map(|t| t.cast(FloatDType::F32)));
    }
    times.sort_by(f64::total_cmp);
    let results = last.context("no pass ran")?;
    Ok((results, times[times.len() / 2]))
}

#[cfg(test)]
mod tests {
    use crate::args::{BenchLinearArgs, PrecisionArg};

    fn args(shapes: &[&str]) -> BenchLinearArgs {
        BenchLinearArgs {
            device: "cpu".into(),
            shapes: shapes.iter().map(|s| s.to_string()).collect(),
            dtypes: vec![PrecisionArg::F32, PrecisionArg::Bf16],
            iters: 1,
        }
    }

    #[test]
    fn runs_on_the_cpu_and_refuses_batched_shapes_by_name() {
        super::run(&args(&["6x5x4"])).expect("bench on the CPU");
        let e = super::run(&args(&["2x6x5x4"])).unwrap_err().to_string();
        assert!(e.contains("`2x6x5x4`"), "{e}");
    }
}
