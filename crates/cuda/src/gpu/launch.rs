//! Launching a checked operation: its kernel with the grid its source expects, or cuBLAS.

use super::exec::{CudaExec, device};
use crate::ops::{Elem, Gemm, Op};
use cudarc::cublas::{result as blas, sys as blas_sys};
use cudarc::driver::{CudaFunction, DeviceRepr, LaunchConfig, PushKernelArg, sys};
use std::collections::HashMap;
use std::ffi::c_void;

/// Warps per block of every kernel but the tiled attention (4).
const WARPS: usize = 8;

/// Warps that share a column of `umgen_gemv` (`gemv_split` of `gemv.cu`): each takes at most 1,024 inputs.
fn gemv_split(k: usize) -> usize {
    let mut split = 1;
    while split < WARPS && split * 1024 < k {
        split *= 2;
    }
    split
}

fn blocks(n: usize, per: usize) -> u32 {
    u32::try_from(n.div_ceil(per).max(1)).unwrap_or(u32::MAX)
}

/// Launches `op`, which `check` has passed.
pub(super) fn launch(x: &CudaExec, op: &Op) -> Result<(), ExecError> {
    let threads = (32 * WARPS) as u32;
    match op {
        Op::Gemv(g) => kernel(
            x,
            "umgen_gemv",
            &x.gemv(g),
            blocks(g.n, WARPS / gemv_split(g.k)).min(x.gemv_blocks),
            threads,
        ),
        Op::Gemm(g) => gemm(x, g),
        Op::AttendRows(t) => kernel(
            x,
            "umgen_attend_rows",
            &x.attend_rows(t),
            blocks(t.batches * t.rows * t.heads * t.splits, 1),
            threads,
        ),
        Op::AttendTiles(t) => kernel(
            x,
            "umgen_attend_tiles",
            &x.attend_tiles(t),
            blocks(t.instances * t.heads * t.lq.div_ceil(32), 1),
            128,
        ),
        Op::Flash(f) => {
            let name = match f.dh {
                32 => "umgen_flash2_forward_bf16_32",
                _ => "umgen_flash2_forward_bf16_64",
            };
            let functions = x
                .flash
                .as_ref()
                .ok_or_else(|| ExecError::Invalid("this executor has no flash2 kernels".into()))?;
            let bh = f.batch * f.heads;
            let grid = (
                blocks(f.lq, 16 * WARPS),
                bh.min(FLASH_GRID_YZ) as u32,
                bh.div_ceil(FLASH_GRID_YZ) as u32,
            );
            launch_3d(x, functions, name, &x.flash2(f), grid, threads)
        }
        Op::Rows(r) => {
            let name = match x.allocs.get(r.dst.id as usize).map(|a| a.elem) {
                Some(Elem::F32) => "umgen_rows_f",
                _ => "umgen_rows_t",
            };
            kernel(x, name, &x.rows(r), blocks(r.rows, WARPS), threads)
        }
        Op::BiasT(b) => kernel(
            x,
            "umgen_bias_t",
            &x.bias_t(b),
            blocks(b.rows, 1).min(1 << 20),
            threads,
        ),
        Op::Embed(e) => kernel(x, "umgen_embed", &x.embed(e), blocks(e.rows, WARPS), threads),
        Op::Shift(s) => kernel(
            x,
            "umgen_shift_block",
            &x.shift(s),
            blocks(s.m * s.len * s.d, 256),
            threads,
        ),
        Op::Align(a) => kernel(
            x,
            "umgen_align",
            &x.align(a),
            blocks(a.frames * a.rows * a.cols, 1).min(1 << 20),
            128,
        ),
        Op::Track(t) => kernel(
            x,
            "umgen_track",
            &x.track(t),
            blocks(t.frames * t.slots, 256),
            threads,
        ),
        Op::Draw(d) => kernel(x, "umgen_draw", &x.draw(d), blocks(d.m, 1), threads),
    }
}

use crate::ops::ExecError;

/// Launches kernel `name` with `params` on `grid` blocks of `threads` threads.
fn kernel<P: DeviceRepr>(
    x: &CudaExec,
    name: &'static str,
    params: &P,
    grid: u32,
    threads: u32,
) -> Result<(), ExecError> {
    if !x.dependent_launch {
        return launch_3d(x, &x.functions, name, params, (grid, 1, 1), threads);
    }
    let f = x
        .functions
        .get(name)
        .ok_or_else(|| ExecError::Device(format!("kernel {name} was not compiled")))?;
    // Programmatic dependent launch: the kernel may start while the one before it finishes; every engine
    // kernel waits (`griddep_wait`) before it reads anything an earlier kernel writes.
    // SAFETY: a zeroed union is a valid value for its integer members; the one set is the attribute's.
    let mut value: sys::CUlaunchAttributeValue = unsafe { std::mem::zeroed() };
    value.programmaticStreamSerializationAllowed = 1;
    let mut attribute = sys::CUlaunchAttribute {
        id: sys::CUlaunchAttributeID::CU_LAUNCH_ATTRIBUTE_PROGRAMMATIC_STREAM_SERIALIZATION,
        pad: [0; 4],
        value,
    };
    let config = sys::CUlaunchConfig {
        gridDimX: grid,
        gridDimY: 1,
        gridDimZ: 1,
        blockDimX: threads,
        blockDimY: 1,
        blockDimZ: 1,
        sharedMemBytes: 0,
        hStream: x.stream.cu_stream(),
        attrs: &mut attribute,
        numAttrs: 1,
    };
    let mut args = [(params as *const P).cast_mut().cast::<c_void>()];
    x.ctx
        .bind_to_thread()
        .map_err(|e| device(name)(format!("{e:?}")))?;
    // SAFETY: `check` passed the operation: every buffer its kernel reaches through `params` holds the
    // elements it reaches, of the types it takes; `params` is laid out as the kernel's one parameter and
    // outlives the call (the driver copies it); the kernel waits for its predecessors before it reads what
    // they write.
    unsafe { sys::cuLaunchKernelEx(&config, f.cu_function(), args.as_mut_ptr(), std::ptr::null_mut()) }
        .result()
        .map_err(|e| device(name)(format!("{e:?}")))
}

/// The flash2 grid's largest y (and z) extent.
const FLASH_GRID_YZ: usize = 65_535;

/// Launches kernel `name` of `functions` with `params` on a `grid` of blocks of `threads` threads.
fn launch_3d<P: DeviceRepr>(
    x: &CudaExec,
    functions: &HashMap<&'static str, CudaFunction>,
    name: &'static str,
    params: &P,
    grid: (u32, u32, u32),
    threads: u32,
) -> Result<(), ExecError> {
    let f = functions
        .get(name)
        .ok_or_else(|| ExecError::Device(format!("kernel {name} was not compiled")))?;
    let config = LaunchConfig {
        grid_dim: grid,
        block_dim: (threads, 1, 1),
        shared_mem_bytes: 0,
    };
    // SAFETY: `check` passed the operation: every buffer its kernel reaches through `params` holds the
    // elements it reaches, of the types it takes; `params` is laid out as the kernel's struct.
    unsafe { x.stream.launch_builder(f).arg(params).launch(config) }
        .map(|_| ())
        .map_err(|e| device(name)(format!("{e:?}")))
}

/// `c (+)= a · wᵀ` by `cublasGemmEx` (column-major: `cᵀ = w · aᵀ`, `w` transposed), f32 accumulation and
/// no TF32, so that f32 weights give f32 products.
fn gemm(x: &CudaExec, g: &Gemm) -> Result<(), ExecError> {
    use blas_sys::cublasOperation_t::{CUBLAS_OP_N, CUBLAS_OP_T};
    use blas_sys::cudaDataType::{CUDA_R_16BF, CUDA_R_32F};
    let int = |v: usize| {
        i32::try_from(v).map_err(|_| ExecError::Invalid(format!("cuBLAS: {v} exceeds its 32-bit sizes")))
    };
    let operand = if x.bf16 { CUDA_R_16BF } else { CUDA_R_32F };
    let written = match x.allocs.get(g.c.id as usize).map(|a| a.elem) {
        Some(Elem::F32) => CUDA_R_32F,
        _ => operand,
    };
    let (one, beta) = (1.0f32, if g.accumulate { 1.0f32 } else { 0.0 });
    // SAFETY: `check` passed the operation: `a` holds `rows` rows of `lda` (k read), `w` `n × k`, `c` `rows`
    // rows of `ldc` (n written) of the types given; the scalars are f32 as the compute type asks.
    unsafe {
        blas::gemm_ex(
            x.blas,
            CUBLAS_OP_T,
            CUBLAS_OP_N,
            int(g.n)?,
            int(g.rows)?,
            int(g.k)?,
            (&one as *const f32).cast::<c_void>(),
            x.ptr(g.w) as *const c_void,
            operand,
            int(g.k)?,
            x.ptr(g.a) as *const c_void,
            operand,
            int(g.lda)?,
            (&beta as *const f32).cast::<c_void>(),
            x.ptr(g.c) as *mut c_void,
            written,
            int(g.ldc)?,
            blas_sys::cublasComputeType_t::CUBLAS_COMPUTE_32F,
            blas_sys::cublasGemmAlgo_t::CUBLAS_GEMM_DEFAULT,
        )
    }
    .map_err(|e| device("cublasGemmEx")(format!("{e:?}")))
}
