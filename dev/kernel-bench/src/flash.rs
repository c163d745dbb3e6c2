//! `umgen-kernel-bench attention --flash`: cubecl's fused flash-attention forward kernels (cubek) against burn's
//! decomposed forward pass, on the cases of `bench attention`. burn launches them only in its `autotune`
//! build; the tiled attention's forward pass could call one directly if it is fast and agrees, and this says
//! whether it is.

use crate::args::BenchAttentionArgs;
use crate::attention::Case;
use umgen_cli::device::Device;

/// Measures (CUDA builds only).
pub(super) fn run(a: &BenchAttentionArgs, cases: &[Case], device: Device) -> anyhow::Result<()> {
    match device {
        #[cfg(feature = "cuda")]
        Device::Cuda(i) => cuda::run(a, cases, i),
        _ => anyhow::bail!(
            "`bench attention --flash` times cubecl's CUDA kernels: it needs --device cuda:N (got `{}`; {} \
             case(s) parsed)",
            a.device,
            cases.len()
        ),
    }
}

#[cfg(feature = "cuda")]
mod cuda {
    use super::{BenchAttentionArgs, Case};
    use crate::args::PrecisionArg;
    use crate::attention::rel_err;
    use burn::backend::cuda::CudaDevice;
    use burn::cubecl::cuda::CudaRuntime;
    use burn::tensor::backend::Backend;
    use burn::tensor::module::attention;
    use burn::tensor::ops::AttentionModuleOptions;
    use burn::tensor::{Distribution, FloatDType, Tensor, TensorPrimitive};
    use burn_cubecl::kernel::attention::flash_attention;
    use cubek::attention::launch::{BlueprintStrategy, Strategy};
    use cubek::attention::routines::blackbox_accelerated::BlackboxAcceleratedStrategy;
    use std::io::Write;
    use std::time::Instant;

    type Cb = burn_cubecl::CubeBackend<CudaRuntime, f32, i32, u8>;

    /// The flash kernels burn's autotuning chooses between, by name.
    fn kernels() -> Vec<(String, Strategy)> {
        let mut v: Vec<(String, Strategy)> = [2u8, 4, 8]
            .into_iter()
            .map(|num_planes| {
                let s = BlackboxAcceleratedStrategy {
                    num_planes,
                    seq_q: 1,
                    seq_kv: 1,
                };
                (
                    format!("flash, tensor cores, {num_planes} planes"),
                    Strategy::BlackboxAccelerated(BlueprintStrategy::Inferred(s)),
                )
            })
            .collect();
        v.push((
            "flash, unit".into(),
            Strategy::Unit(BlueprintStrategy::Inferred(())),
        ));
        v
    }

    /// Median seconds of `iters` synced runs of `f` after one untimed run, and the last output.
    fn time(
        iters: usize,
        dev: &CudaDevice,
        f: &dyn Fn() -> Result<Tensor<Cb, 4>, String>,
    ) -> Result<(f64, Tensor<Cb, 4>), String> {
        let mut out = f()?;
        let mut t = Vec::with_capacity(iters);
        for _ in 0..iters {
            let t0 = Instant::now();
            out = f()?;
            Cb::sync(dev).map_err(|e| format!("{e:?}"))?;
            t.push(t0.elapsed().as_secs_f64());
        }
        t.sort_by(f64::total_cmp);
        Ok((t[t.len() / 2], out))
    }

    pub(super) fn run(a: &BenchAttentionArgs, cases: &[Case], gpu: usize) -> anyhow::Result<()> {
        let dev = CudaDevice::new(gpu);
        let mut out = std::io::stdout().lock();
        writeln!(
            out,
            "attention forward on cuda:{gpu}, flash operands in {}, median of {} runs; err = max|Δ| / \
             max|decomposed|",
            a.precision.name(),
            a.iters.max(1)
        )?;
        writeln!(out, "{:<22} {:<34} {:>10} {:>9}", "case", "kernel", "ms", "err")?;
        for (c, name) in cases.iter().zip(&a.cases) {
            let n = Distribution::Normal(0.0, 1.0);
            let q = Tensor::<Cb, 4>::random([c.seqs, c.heads, c.lq, c.dh], n, &dev);
            let k = Tensor::<Cb, 4>::random([c.seqs, c.heads, c.lk, c.dh], n, &dev);
            let v = Tensor::<Cb, 4>::random([c.seqs, c.heads, c.lk, c.dh], n, &dev);
            let opts = || AttentionModuleOptions {
                is_causal: c.causal,
                ..Default::default()
            };
            // Without the `autotune` build burn's attention is the decomposed fallback.
            let decomposed = || Ok(attention(q.clone(), k.clone(), v.clone(), None, None, opts()));
            let (secs, reference) = time(a.iters.max(1), &dev, &decomposed).map_err(anyhow::Error::msg)?;
            writeln!(
                out,
                "{name:<22} {:<34} {:>10.3} {:>9}",
                "decomposed (burn, f32)",
                1e3 * secs,
                "-"
            )?;
            // The flash kernels read the operands in `--precision`'s format.
            let dtype = match a.precision {
                PrecisionArg::F32 => FloatDType::F32,
                PrecisionArg::Bf16 => FloatDType::BF16,
            };
            let (q, k, v) = (q.cast(dtype), k.cast(dtype), v.cast(dtype));
            for (kname, strategy) in kernels() {
                let flash = || {
                    let (qp, kp, vp) = (
                        q.clone().into_primitive().tensor(),
                        k.clone().into_primitive().tensor(),
                        v.clone().into_primitive().tensor(),
                    );
                    // Some kernels assert on shapes they cannot tile instead of returning an error.
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                        flash_attention(qp, kp, vp, None, None, opts(), strategy.clone())
                    }))
                    .map_err(|_| "panicked".to_string())?
                    .map(|t| Tensor::from_primitive(TensorPrimitive::Float(t)))
                    .map_err(|e| format!("{e:?}"))
                };
                let (ms, err) = match time(a.iters.max(1), &dev, &flash) {
                    Ok((s, o)) => (
                        format!("{:.3}", 1e3 * s),
                        format!("{:.1e}", rel_err(o.cast(FloatDType::F32), reference.clone())),
                    ),
                    Err(e) => ("-".into(), crate::matmul::one_line(&e, 90)),
                };
                writeln!(out, "{name:<22} {kname:<34} {ms:>10} {err:>9}")?;
                out.flush()?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::args::{BenchAttentionArgs, PrecisionArg};

    #[test]
    fn flash_needs_cuda_and_says_so() {
        let a = BenchAttentionArgs {
            device: "cpu".into(),
            cases: vec!["1x1x4x4x8c".into()],
            iters: 1,
            precision: PrecisionArg::F32,
            flash: true,
            block_mib: vec![],
            kernels: vec![],
            backward: vec![],
            step: vec![],
        };
        let e = crate::attention::run(&a).unwrap_err().to_string();
        assert!(
            e.contains("--flash") && e.contains("`cpu`") && e.contains("1 case"),
            "{e}"
        );
    }
}
