//! [`CudaExec`]'s state (context, stream, kernels, cuBLAS handle, buffers, graphs) and its buffer access,
//! which the launch code and the kernels' parameters read.
#![allow(unsafe_code)]

use crate::ops::{Buf, Elem, ExecError};
use cudarc::cublas::sys as blas_sys;
use cudarc::driver::{CudaContext, CudaFunction, CudaGraph, CudaStream, result};
use std::collections::HashMap;
use std::sync::Arc;

/// One allocation.
pub(super) struct Alloc {
    pub(super) ptr: u64,
    pub(super) elem: Elem,
    pub(super) len: usize,
}

/// The engine's operations on a GPU.
pub struct CudaExec {
    pub(super) ctx: Arc<CudaContext>,
    pub(super) stream: Arc<CudaStream>,
    pub(super) functions: HashMap<&'static str, CudaFunction>,
    /// FlashAttention-2's forward kernels (bf16 executors on compute capability 8.0 or newer).
    pub(super) flash: Option<HashMap<&'static str, CudaFunction>>,
    /// Whether the engine's kernels launch with programmatic dependent launch (compute capability 9.0;
    /// `UMGEN_DEPENDENT_LAUNCH=0` turns it off, for comparison).
    pub(super) dependent_launch: bool,
    /// Blocks of `umgen_gemv` that fit on the GPU at once (SMs × resident blocks): its grid walks the
    /// columns, so one wave streams every weight and no block waits for a second one.
    pub(super) gemv_blocks: u32,
    pub(super) blas: blas_sys::cublasHandle_t,
    pub(super) allocs: Vec<Alloc>,
    pub(super) graphs: HashMap<u64, CudaGraph>,
    pub(super) bf16: bool,
    pub(super) bytes: usize,
}

pub(super) fn device(what: &str) -> impl Fn(String) -> ExecError + '_ {
    move |e| ExecError::Device(format!("{what}: {e}"))
}

/// NVRTC's architecture for compute capability `major.minor`, where NVRTC 13 knows it.
pub(super) fn arch(major: i32, minor: i32) -> Option<&'static str> {
    Some(match (major, minor) {
        (7, 5) => "compute_75",
        (8, 0) => "compute_80",
        (8, 6) => "compute_86",
        (8, 7) => "compute_87",
        (8, 9) => "compute_89",
        (9, 0) => "compute_90",
        (10, 0) => "compute_100",
        (12, 0) => "compute_120",
        _ => return None,
    })
}

impl CudaExec {
    /// Bytes of the device's memory in use by every process and context (total − free).
    pub fn device_memory(&self) -> Result<usize, ExecError> {
        let (free, total) = self
            .ctx
            .mem_get_info()
            .map_err(|e| device("memory info")(format!("{e:?}")))?;
        Ok(total.saturating_sub(free))
    }

    /// The device's name.
    pub fn name(&self) -> String {
        self.ctx.name().unwrap_or_else(|_| "CUDA device".into())
    }

    /// Bytes of an element of `elem`.
    pub(super) fn size(&self, elem: Elem) -> usize {
        match elem {
            Elem::W if self.bf16 => 2,
            Elem::U8 => 1,
            Elem::F64 => 8,
            Elem::Rule => size_of::<crate::ops::Rule>(),
            Elem::Run => size_of::<crate::ops::GroupRun>(),
            _ => 4,
        }
    }

    /// The allocation of `b`, checked to hold `len` elements of one of `kinds` from `b.at` on.
    pub(super) fn alloc_of(
        &self,
        b: Buf,
        len: usize,
        kinds: &[Elem],
        what: &str,
    ) -> Result<&Alloc, ExecError> {
        let a = self.allocs.get(b.id as usize).ok_or_else(|| ExecError::Missing {
            what: what.into(),
            id: b.id,
        })?;
        if !kinds.contains(&a.elem) {
            return Err(ExecError::Kind {
                what: what.into(),
                id: b.id,
                found: a.elem,
                want: kinds.to_vec(),
            });
        }
        if b.at + len > a.len {
            return Err(ExecError::Bounds {
                what: what.into(),
                id: b.id,
                end: b.at + len,
                len: a.len,
            });
        }
        Ok(a)
    }

    /// The device address of element `b.at` of `b`'s allocation (checked by the caller).
    pub(super) fn ptr(&self, b: Buf) -> u64 {
        self.allocs
            .get(b.id as usize)
            .map_or(0, |a| a.ptr + (b.at * self.size(a.elem)) as u64)
    }

    /// Copies `bytes` host bytes to `b` (checked by the caller).
    pub(super) fn upload(&self, b: Buf, bytes: &[u8]) -> Result<(), ExecError> {
        // SAFETY: the caller checked that the allocation holds `bytes.len()` bytes from `b`; pageable host
        // memory is staged before the call returns, so `bytes` may go.
        unsafe { result::memcpy_htod_async(self.ptr(b), bytes, self.stream.cu_stream()) }
            .map_err(|e| device("copy to the device")(format!("{e:?}")))
    }

    /// `out.len()` bytes from `b` (checked by the caller), after everything queued.
    pub(super) fn download(&self, b: Buf, out: &mut [u8]) -> Result<(), ExecError> {
        // SAFETY: the caller checked the extent; the stream is synchronised before `out` is read.
        unsafe { result::memcpy_dtoh_async(out, self.ptr(b), self.stream.cu_stream()) }
            .map_err(|e| device("copy to the host")(format!("{e:?}")))?;
        self.stream
            .synchronize()
            .map_err(|e| device("synchronize")(format!("{e:?}")))
    }

    /// Drops every captured graph and waits for the stream, before memory they may name is freed.
    pub(super) fn forget_graphs(&mut self) {
        self.graphs.clear();
        let _ = self.stream.synchronize();
    }
}
