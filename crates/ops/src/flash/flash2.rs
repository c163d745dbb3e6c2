//! Launches the `flash2` kernels (umgen-cuda's `kernels/flash2/`: `flash2_warp.cu`, `flash2_tiles.cu` and
//! `flash2.cu`, CUDA C compiled with
//! NVRTC) on cubecl's stream (or, with `train.kernels.stream = "side"`, on a side stream ordered with
//! cubecl's), on burn's buffers as they lie in memory.
//!
//! They are FlashAttention-2 as its authors wrote it: `mma.sync` products with scores, probabilities and
//! their gradients in registers, which cubecl's `cmma` abstraction cannot express (its fragments are
//! opaque, so the softmax of the `fused` kernels goes through shared memory). Head sizes 32 and 64, f32 or
//! bf16 operands (rounded to bf16 on the way into shared memory), compute capability 8.0 or newer; the
//! caller runs the `fused` kernels for anything else. On a compute capability 9.0 device both streams
//! compile them for `sm_90a` (cubecl always does; `build` asks for `compute_90a`), and there the head size
//! 64 products run on Hopper's `wgmma` (docs/decisions/005-training-attention-flash2.md). `flash2_emulator.cpp` checks the fragment
//! layouts on the host.
#![allow(unsafe_code)]

use crate::kernels::{Flash2Backward, KernelStream, Kernels, SideFamily};
use crate::side::Primitive;
use crate::side::{Compiled, KernelCache, Pointers, launch_on_cubecl, launch_shared_on_cubecl, with_cached};
use crate::side::{empty_f32, empty_packed};
use burn::tensor::DType;
use cudarc::driver::{CudaFunction, LaunchConfig, PushKernelArg};
use cudarc::nvrtc::CompileOptions;
use std::cell::RefCell;
// `Params` of `flash2_tiles.cu`, field for field (one definition, shared with the generation engine).
use umgen_cuda::gpu::Flash2 as Params;

/// The kernels' source: the GPU's primitives, the building blocks, then the three passes.
const SOURCE: &str = umgen_cuda::source::FLASH2;

/// The grid's largest y (and z) extent.
const GRID_YZ: usize = 65_535;

/// Dynamic shared memory of the one-pass backward kernel: `ONE_PASS_SHARED` of `flash2_dq.cu` (two bf16
/// tiles of dS, 128 keys × (column step + 8), then an f32 tile of a step's dQ, column step × 64) for the
/// largest column step, 64 (`SUB`, which a source given by `UMGEN_FLASH2_SOURCE` may change).
const ONE_PASS_SHARED: usize = 2 * 128 * (64 + 8) * 2 + 64 * 64 * 4;

/// The kernels' source: [`SOURCE`], or the file `UMGEN_FLASH2_SOURCE` names (for trying a change to the
/// kernels without rebuilding umgen: `cat flash2_warp.cu flash2_tiles.cu flash2_dq.cu flash2.cu > FILE`, then edit; it must keep the
/// kernels' names and `Params`).
fn source() -> Result<String, String> {
    match std::env::var_os("UMGEN_FLASH2_SOURCE") {
        Some(path) => std::fs::read_to_string(&path)
            .map_err(|e| format!("UMGEN_FLASH2_SOURCE {}: {e}", path.to_string_lossy())),
        None => Ok(SOURCE.to_string()),
    }
}

/// Why the kernels cannot take operands of head size `d` and type `dtype`, if they cannot.
pub(super) fn unfit(d: usize, dtype: DType) -> Option<String> {
    if d != 32 && d != 64 {
        return Some(format!("head size {d} (the flash2 kernels take 32 and 64)"));
    }
    (!matches!(dtype, DType::F32 | DType::BF16))
        .then(|| format!("{dtype:?} operands (the flash2 kernels take f32 and bf16)"))
}

thread_local! {
    /// This thread's kernels by device.
    static KERNELS: KernelCache = const { RefCell::new(Vec::new()) };
}

/// Compiles the kernels for `like`'s device and logs their resources: for compute capability 9.0 as
/// `compute_90a` (Hopper's `wgmma` for head size 64, as cubecl's stream compiles them), else 8.0 (bf16
/// `mma.sync`).
fn build(like: &Primitive, warps: usize) -> Result<Compiled, String> {
    let options = |major: i32| CompileOptions {
        arch: Some(if major == 9 { "compute_90a" } else { "compute_80" }),
        use_fast_math: Some(true),
        ..Default::default()
    };
    let mut names = Vec::new();
    for pass in ["forward", "backward_kv", "backward_q"] {
        for dtype in ["f32", "bf16"] {
            for d in [32, 64] {
                names.push(format!("umgen_flash2_{pass}_{dtype}_{d}"));
            }
        }
    }
    let kernels = Compiled::compile(like, source()?, options, &names, 8)?;
    tracing::info!(
        "flash2 kernels compiled: {}",
        resources(kernels.functions(), warps)
    );
    Ok(kernels)
}

/// Registers, spilled bytes and blocks per SM of the head-size-64 kernels: what limits their occupancy.
fn resources(functions: &[(String, CudaFunction)], warps: usize) -> String {
    let threads = 32 * warps as u32;
    functions
        .iter()
        .filter(|(name, _)| name.ends_with("_64"))
        .map(|(name, f)| {
            let short = name.trim_start_matches("umgen_flash2_");
            match (
                f.num_regs(),
                f.local_size_bytes(),
                f.occupancy_max_active_blocks_per_multiprocessor(threads, 0, None),
            ) {
                (Ok(r), Ok(l), Ok(b)) => format!("{short} {r} registers, {l} B spilled, {b} blocks/SM"),
                _ => format!("{short} (attributes unavailable)"),
            }
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// Whether the backward pass tries the one-pass kernels: asked for, on cubecl's stream (`Kernels::problem`
/// refuses them elsewhere). They take head size 64 where NVRTC targets `sm_90a`; elsewhere their first
/// launch fails and the two-pass kernels run.
fn one_pass(kernels: &Kernels) -> bool {
    kernels.attention_backward == Flash2Backward::OnePass && kernels.stream == KernelStream::Cubecl
}

/// `[b, rows, h, d]` as the `[b, h, rows, d]` view the attention's callers take (no copy).
fn heads_first(t: Primitive) -> Primitive {
    crate::side::inner(crate::format::float::<crate::side::Inner, 4>(t).swap_dims(1, 2))
}

/// The strides (batch, head, row) of a `[b, h, rows, d]` operand whose last dimension is contiguous.
fn strides(t: &Primitive, what: &str) -> Result<[i64; 3], String> {
    let (shape, s) = (t.meta.shape(), t.meta.strides());
    if shape.len() != 4 || (s[3] != 1 && shape[3] > 1) {
        return Err(format!("{what}: shape {shape:?}, strides {s:?}"));
    }
    let int = |x: usize| i64::try_from(x).map_err(|_| format!("{what}: stride {x}"));
    Ok([int(s[0])?, int(s[1])?, int(s[2])?])
}

/// Runs the forward pass on `q`, `k`, `v` (`grads` `None`: the output `[b, h, lq, d]` and the log-sum-exp)
/// or the backward pass (`grads` = `[dout, lse, delta]`: dq `[b, h, lq, d]` and the keys' and values'
/// gradients as one `[b, lk, 2·h, d]`, keys' heads first), returning its results in the operands' format
/// (the log-sum-exp f32); an error says why it could not (no result was written that the caller keeps, so the caller may run another path).
///
/// The output and dq are views of buffers laid out merged, `[b, rows, h·d]`, which is how the next product
/// reads them: the head merge after the attention (`layers::merge_heads`) then only relabels them, where a
/// contiguous `[b, h, rows, d]` result took a copy (0.26–0.32 ms each on an H100: 148 ms of `paper`'s
/// step with the keys' and values' concatenation, docs/decisions/005-training-attention-flash2.md).
pub(super) fn launch(
    q: &Primitive,
    k: &Primitive,
    v: &Primitive,
    grads: Option<[&Primitive; 3]>,
    causal: bool,
    kernels: &Kernels,
) -> Result<Vec<Primitive>, String> {
    let s = q.meta.shape();
    let (b, h, lq, d) = (s[0], s[1], s[2], s[3]);
    let lk = k.meta.shape()[2];
    if let Some(why) = unfit(d, q.dtype) {
        return Err(why);
    }
    let mut operands = vec![q, k, v];
    operands.extend(grads.map(|[dout, _, _]| dout));
    if operands.iter().any(|t| t.dtype != q.dtype) {
        return Err("operands of different types".into());
    }
    let bh = b * h;
    if bh == 0 || lq == 0 || lk == 0 {
        return Err("an empty dimension".into());
    }
    // The kernels index heads and rows with 32-bit integers; the grid holds 65,535² heads.
    if bh > GRID_YZ * GRID_YZ || bh > i32::MAX as usize || lq.max(lk) > i32::MAX as usize {
        return Err(format!(
            "{b} × {h} heads of {lq} × {lk}: over the launch grid's limits"
        ));
    }
    // Every value was checked against i32::MAX above.
    let int = |x: usize| x as i32;
    let mut p = Params {
        heads: int(h),
        lq: int(lq),
        lk: int(lk),
        off: int(lk.saturating_sub(lq)),
        causal: i32::from(causal),
        scale: 1.0 / (d as f32).sqrt(),
        count: int(bh),
        qs: strides(q, "q")?,
        ks: strides(k, "k")?,
        vs: strides(v, "v")?,
        ..Params::default()
    };
    // The pointers, and what keeps the buffers alive until the launch is queued.
    let mut keep = Pointers::default();
    let mut ptr = |t: &Primitive| keep.of(t);
    (p.q, p.k, p.v) = (ptr(q)?, ptr(k)?, ptr(v)?);
    let dtype = if q.dtype == DType::BF16 { "bf16" } else { "f32" };
    // The strides (batch, head, row) of a result merged as `[b, rows, heads·d]`.
    let merged = |rows: usize, heads: usize| [(rows * heads * d) as i64, d as i64, (heads * d) as i64];
    // The results, each kernel's name and the rows its grid covers.
    let (results, launches) = match grads {
        None => {
            let out = empty_packed(q, vec![b, lq, h, d], q.dtype);
            let results = vec![heads_first(out.clone()), empty_f32(q, vec![b, h, lq, 1])];
            (p.out, p.lse_out) = (ptr(&out)?, ptr(&results[1])?);
            p.outs = merged(lq, h);
            (results, vec![(format!("umgen_flash2_forward_{dtype}_{d}"), lq)])
        }
        Some([dout, lse, delta]) => {
            (p.os, p.ls, p.es) = (
                strides(dout, "dout")?,
                strides(lse, "lse")?,
                strides(delta, "delta")?,
            );
            (p.dout, p.lse, p.delta) = (ptr(dout)?, ptr(lse)?, ptr(delta)?);
            let dq = empty_packed(q, vec![b, lq, h, d], q.dtype);
            let dkv = empty_packed(q, vec![b, lk, 2 * h, d], q.dtype);
            (p.dq, p.dk) = (ptr(&dq)?, ptr(&dkv)?);
            // The values' columns follow the keys' in each row.
            p.dv = p.dk + (h * d * q.dtype.size()) as u64;
            (p.dqs, p.dks, p.dvs) = (merged(lq, h), merged(lk, 2 * h), merged(lk, 2 * h));
            if one_pass(kernels) {
                if d == 64 {
                    let acc = empty_f32(q, vec![b, h, lq, d]);
                    p.dq_acc = ptr(&acc)?;
                } else {
                    let why = format!("head size {d} (its kernels take 64)");
                    super::fell_back("flash2 one-pass", &why, "two-pass flash2");
                }
            }
            let results = vec![heads_first(dq), dkv];
            let launches = vec![
                (format!("umgen_flash2_backward_kv_{dtype}_{d}"), lk),
                (format!("umgen_flash2_backward_q_{dtype}_{d}"), lq),
            ];
            (results, launches)
        }
    };
    // Warps per block (each owns 16 rows), 4 or 8: 8 was 10–18 % faster on an H100
    // (docs/decisions/005-training-attention-flash2.md).
    let warps = kernels.flash2_warps;
    let grid = |rows: usize| {
        (
            rows.div_ceil(16 * warps) as u32,
            bh.min(GRID_YZ) as u32,
            bh.div_ceil(GRID_YZ) as u32,
        )
    };
    let threads = 32 * warps as u32;
    if kernels.stream == KernelStream::Cubecl {
        let element = if dtype == "bf16" { "u16" } else { "float" };
        if p.dq_acc != 0 {
            let instance = format!("ONE_PASS_64({dtype}_64, {element})");
            let launches = [
                (format!("umgen_flash2_dq_zero_{dtype}_64"), lq, 0),
                (
                    format!("umgen_flash2_backward_one_pass_{dtype}_64"),
                    lk,
                    ONE_PASS_SHARED,
                ),
                (format!("umgen_flash2_dq_store_{dtype}_64"), lq, 0),
            ];
            // SAFETY: as the two-pass launches below; `dq_acc` is a live `[b, h, lq, 64]` f32 buffer.
            let launched = launches.iter().try_for_each(|(name, rows, shared)| unsafe {
                launch_shared_on_cubecl(q, name, (&instance, &source), (grid(*rows), threads, *shared), &p)
            });
            match launched {
                Ok(()) => return Ok(results),
                // The two-pass kernels write every result the one-pass ones may have begun.
                Err(why) => super::fell_back("flash2 one-pass", &why, "two-pass flash2"),
            }
        }
        let instance = format!("INSTANCES({dtype}_{d}, {element}, {d})");
        for (name, rows) in &launches {
            // SAFETY: every pointer in `p` is a live buffer (kept by `keep`) of the shape and strides recorded
            // beside it, made on `q`'s stream.
            unsafe { launch_on_cubecl(q, name, (&instance, &source), grid(*rows), threads, &p) }?;
        }
        return Ok(results);
    }
    with_cached(
        &KERNELS,
        q,
        "flash2 attention",
        || build(q, warps),
        |compiled| {
            let functions = launches
                .iter()
                .map(|(name, rows)| Ok((name, *rows, compiled.function(name)?.clone())))
                .collect::<Result<Vec<_>, String>>()?;
            compiled
                .side
                .ordered((SideFamily::Attention, kernels.side_sync), |stream| {
                    for (name, rows, f) in &functions {
                        let config = LaunchConfig {
                            grid_dim: grid(*rows),
                            block_dim: (threads, 1, 1),
                            shared_mem_bytes: 0,
                        };
                        // SAFETY: every pointer in `p` is a live buffer (kept by `keep`) of the shape and strides
                        // recorded beside it, and cubecl's stream waits for the kernels before anything queued later
                        // can free or reuse them.
                        unsafe { stream.launch_builder(f).arg(&p).launch(config) }
                            .map_err(|e| format!("{name}: {e:?}"))?;
                    }
                    Ok(())
                })
        },
    )?;
    Ok(results)
}
