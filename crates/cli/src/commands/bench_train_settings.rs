//! The lines of `umgen bench train`'s report that say how the step ran rather than how fast: the kernel
//! choices and how often each fell back, activation recomputation, the ranks and where the optimizer
//! state lives.

use crate::device::Device;
use std::io::Write;
use umgen::train::TrainConfig;

/// Writes the settings lines for a step on `device` under `tc`, over `world` ranks of group `backend`.
pub(super) fn write(
    out: &mut impl Write,
    device: &Device,
    tc: &TrainConfig,
    world: usize,
    backend: &str,
) -> std::io::Result<()> {
    // Only the CUDA training backend has cuBLAS and the named kernel; elsewhere `matmul` changes nothing.
    #[cfg(feature = "cuda")]
    if matches!(device, Device::Cuda(_)) {
        writeln!(
            out,
            "matmul        {:?}, {} product(s) fell back (cuBLAS to the named kernel, or it to burn's; \
             the first is logged with its reason)",
            tc.kernels.matmul,
            umgen::ops::matmul::fallbacks()
        )?;
    }
    // Likewise the fused attention and layer-norm kernels.
    if matches!(device, Device::Cuda(_)) {
        writeln!(
            out,
            "attention     {:?}, {} pass(es) fell back (flash2 to the fused kernels, or those to the tiled; \
             the first is logged with its reason)",
            tc.kernels.attention,
            umgen::ops::flash::fallbacks()
        )?;
        writeln!(
            out,
            "layer norm    {} pass(es) fell back (the CUDA kernels to burn's decomposition; the first is \
             logged with its reason)",
            umgen::ops::norm::fallbacks()
        )?;
        writeln!(
            out,
            "bias + GELU   {:?}, {} pass(es) fell back (the CUDA kernels to burn's operations; the first is \
             logged with its reason)",
            tc.kernels.gelu,
            umgen::ops::gelu::fallbacks()
        )?;
        writeln!(
            out,
            "cross-entropy {:?}, {} pass(es) fell back (the CUDA kernels to burn's operations; the first is \
             logged with its reason)",
            tc.kernels.xent,
            umgen::ops::xent::fallbacks()
        )?;
        writeln!(
            out,
            "embedding     {} table gradient(s) fell back (the CUDA kernels to the scatter; the first is logged \
             with its reason)",
            umgen::ops::lookup::fallbacks()
        )?;
        writeln!(
            out,
            "row sums      {} sum(s) fell back (the CUDA kernel to burn's reductions; the first is logged with \
             its reason)",
            umgen::ops::rows::fallbacks()
        )?;
        writeln!(
            out,
            "adamw         {:?}, {} step(s) fell back (the CUDA kernel to burn's AdamW or its arithmetic; the \
             first is logged with its reason), gradients clipped at {}",
            tc.kernels.adamw,
            umgen::ops::adamw::fallbacks(),
            tc.grad_clip
        )?;
        writeln!(
            out,
            "launches      from the {:?} thread (umgen's kernels and cuBLAS's products)",
            tc.kernels.launch_thread
        )?;
    }
    writeln!(
        out,
        "recompute     {}",
        if tc.kernels.recompute {
            format!(
                "on: {} layer passes (self-attention, and cross-attention without a mask) kept only their inputs",
                umgen::ops::layer::layers_recomputed()
            )
        } else {
            "off".into()
        }
    )?;
    if !tc.kernels.recompute && tc.kernels.layer == umgen::ops::kernels::LayerKernel::Fused {
        writeln!(
            out,
            "layers        one operation each: {} layer passes kept their activations",
            umgen::ops::layer::layers_kept()
        )?;
    }
    if world > 1 {
        writeln!(
            out,
            "ranks         {world} ({backend}), gradient buckets of {:.0} MiB, optimizer state {}",
            tc.bucket_mib,
            if tc.shard_optimizer {
                "sharded (train.shard_optimizer)"
            } else {
                "on every rank"
            }
        )?;
    }
    Ok(())
}
