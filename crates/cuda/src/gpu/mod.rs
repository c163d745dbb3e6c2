//! [`CudaExec`]: the engine's operations on one GPU, on one stream of the device's primary context.
//!
//! Buffers are plain `cuMemAlloc` allocations, freed when the executor is dropped. The kernels are compiled
//! by NVRTC once, for the device's architecture and the weights' element type, as machine code kept in a
//! cache (`compile.rs`, `cubin.rs`). Event tracking (cudarc's ordering of its own buffers across streams) is
//! off: everything runs on one stream, and a sequence captured as a graph must contain only kernel launches
//! and cuBLAS calls.
#![allow(unsafe_code)]

mod compile;
mod cubin;
mod exec;
mod launch;
mod params;

pub use exec::CudaExec;
use exec::{Alloc, arch, device};

pub use params::Flash2;

use crate::ops::{Buf, Data, Elem, Exec, ExecError, Op, check};
use cudarc::cublas::{result as blas, sys as blas_sys};
use cudarc::driver::{CudaContext, result, sys};
use std::collections::HashMap;

impl CudaExec {
    /// An executor on GPU `ordinal` whose `W` buffers hold bf16 (`bf16`) or f32; compiles the kernels.
    pub fn new(ordinal: usize, bf16: bool) -> Result<Self, ExecError> {
        let ctx = CudaContext::new(ordinal).map_err(|e| device("CUDA context")(format!("{e:?}")))?;
        // SAFETY: this executor orders its work on its one stream itself and never hands out cudarc slices.
        unsafe { ctx.disable_event_tracking() };
        let stream = ctx.new_stream().map_err(|e| device("stream")(format!("{e:?}")))?;
        let (major, minor) = ctx
            .compute_capability()
            .map_err(|e| device("compute capability")(format!("{e:?}")))?;
        let (functions, flash) = compile::kernels(&ctx, (major, minor), bf16)?;
        let sms = ctx
            .attribute(sys::CUdevice_attribute::CU_DEVICE_ATTRIBUTE_MULTIPROCESSOR_COUNT)
            .map_err(|e| device("SM count")(format!("{e:?}")))?;
        let resident = functions
            .get("umgen_gemv")
            .ok_or_else(|| ExecError::Invalid("the engine source has no umgen_gemv".into()))?
            .occupancy_max_active_blocks_per_multiprocessor(256, 0, None)
            .map_err(|e| device("umgen_gemv occupancy")(format!("{e:?}")))?;
        let gemv_blocks = (sms.max(1) as u32).saturating_mul(resident.max(1));
        // SAFETY: only asks whether the library could be loaded.
        if !unsafe { blas_sys::is_culib_present() } {
            return Err(ExecError::Device(
                "libcublas (CUDA 13: libcublas.so.13) is not on the library path".into(),
            ));
        }
        let handle = blas::create_handle().map_err(|e| device("cublasCreate")(format!("{e:?}")))?;
        // SAFETY: a live handle and this executor's stream, which outlives it (both are dropped together).
        unsafe { blas::set_stream(handle, stream.cu_stream() as blas_sys::cudaStream_t) }
            .map_err(|e| device("cublasSetStream")(format!("{e:?}")))?;
        Ok(Self {
            ctx,
            stream,
            functions,
            flash,
            dependent_launch: major >= 9
                && std::env::var("UMGEN_DEPENDENT_LAUNCH").map_or(true, |v| v != "0"),
            gemv_blocks,
            blas: handle,
            allocs: Vec::new(),
            graphs: HashMap::new(),
            bf16,
            bytes: 0,
        })
    }

    /// Runs `op` without checking it (callers check first).
    fn launch(&self, op: &Op) -> Result<(), ExecError> {
        launch::launch(self, op)
    }
}

impl Exec for CudaExec {
    fn alloc(&mut self, elem: Elem, len: usize) -> Result<Buf, ExecError> {
        // Whole 256-byte blocks, so that every allocation starts aligned and can take 16-byte loads.
        let bytes = (len.max(1) * self.size(elem)).div_ceil(256) * 256;
        self.ctx
            .bind_to_thread()
            .map_err(|e| device("binding the context")(format!("{e:?}")))?;
        // SAFETY: a plain allocation of the bound context, zeroed on this executor's stream before use.
        let ptr = unsafe { result::malloc_sync(bytes) }.map_err(|e| {
            device("cuMemAlloc")(format!("{e:?} ({:.2} GiB)", bytes as f64 / (1u64 << 30) as f64))
        })?;
        // SAFETY: `ptr` holds `bytes` bytes.
        unsafe { result::memset_d8_async(ptr, 0, bytes, self.stream.cu_stream()) }
            .map_err(|e| device("zeroing")(format!("{e:?}")))?;
        let id =
            u32::try_from(self.allocs.len()).map_err(|_| ExecError::Invalid("too many buffers".into()))?;
        self.allocs.push(Alloc { ptr, elem, len });
        self.bytes += bytes;
        Ok(Buf { id, at: 0 })
    }

    fn free(&mut self, id: u32) {
        let Some((ptr, len, elem)) = self.allocs.get(id as usize).map(|a| (a.ptr, a.len, a.elem)) else {
            return;
        };
        if ptr == 0 {
            return;
        }
        // Graphs may name it: they go first. The stream finishes what may still read it.
        self.forget_graphs();
        // SAFETY: this executor's own allocation, no longer used by queued work (synchronised above) nor by
        // any graph; its entry keeps no pointer, so nothing reaches it again.
        let _ = unsafe { result::free_sync(ptr) };
        self.bytes -= (len.max(1) * self.size(elem)).div_ceil(256) * 256;
        if let Some(a) = self.allocs.get_mut(id as usize) {
            (a.ptr, a.len) = (0, 0);
        }
    }

    fn write(&mut self, dst: Buf, data: Data<'_>) -> Result<(), ExecError> {
        let a = self.alloc_of(dst, data.len(), data.kinds(), "write")?;
        let bytes: Vec<u8> = match data {
            Data::F32(d) if a.elem == Elem::W && self.bf16 => {
                le_bytes(d, |x, o: &mut [u8; 2]| *o = bf16_bits(x).to_le_bytes())
            }
            Data::F32(d) => le_bytes(d, |x, o: &mut [u8; 4]| *o = x.to_le_bytes()),
            Data::I32(d) => le_bytes(d, |x, o: &mut [u8; 4]| *o = x.to_le_bytes()),
            Data::U32(d) => le_bytes(d, |x, o: &mut [u8; 4]| *o = x.to_le_bytes()),
            Data::U8(d) => d.to_vec(),
            Data::F64(d) => le_bytes(d, |x, o: &mut [u8; 8]| *o = x.to_le_bytes()),
            Data::Rules(d) => d.iter().flat_map(params::rule_bytes).collect(),
            Data::Runs(d) => d.iter().flat_map(params::run_bytes).collect(),
        };
        self.upload(dst, &bytes)
    }

    fn read_f32(&mut self, src: Buf, len: usize) -> Result<Vec<f32>, ExecError> {
        let a = self.alloc_of(src, len, &[Elem::F32, Elem::W], "read")?;
        let wide = !(a.elem == Elem::W && self.bf16);
        let mut bytes = vec![0u8; len * if wide { 4 } else { 2 }];
        self.download(src, &mut bytes)?;
        Ok(if wide {
            bytes
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        } else {
            bytes
                .chunks_exact(2)
                .map(|c| f32::from_bits(u32::from(u16::from_le_bytes([c[0], c[1]])) << 16))
                .collect()
        })
    }

    fn read_i32(&mut self, src: Buf, len: usize) -> Result<Vec<i32>, ExecError> {
        self.alloc_of(src, len, &[Elem::I32], "read")?;
        let mut bytes = vec![0u8; len * 4];
        self.download(src, &mut bytes)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn read_u32(&mut self, src: Buf, len: usize) -> Result<Vec<u32>, ExecError> {
        self.alloc_of(src, len, &[Elem::U32], "read")?;
        let mut bytes = vec![0u8; len * 4];
        self.download(src, &mut bytes)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }

    fn run(&mut self, op: &Op) -> Result<(), ExecError> {
        check(op, |id| self.allocs.get(id as usize).map(|a| (a.elem, a.len)))?;
        self.launch(op)
    }

    fn replay(&mut self, key: u64, ops: &[Op]) -> Result<(), ExecError> {
        if !self.graphs.contains_key(&key) {
            for op in ops {
                check(op, |id| self.allocs.get(id as usize).map(|a| (a.elem, a.len)))?;
            }
            self.stream
                .begin_capture(sys::CUstreamCaptureMode::CU_STREAM_CAPTURE_MODE_THREAD_LOCAL)
                .map_err(|e| device("begin capture")(format!("{e:?}")))?;
            let launched = ops.iter().try_for_each(|op| self.launch(op));
            let graph = self
                .stream
                .end_capture(sys::CUgraphInstantiate_flags(0))
                .map_err(|e| device("end capture")(format!("{e:?}")));
            launched?;
            let graph = graph?.ok_or_else(|| ExecError::Device("an empty capture".into()))?;
            graph
                .upload()
                .map_err(|e| device("graph upload")(format!("{e:?}")))?;
            self.graphs.insert(key, graph);
        }
        match self.graphs.get(&key) {
            Some(g) => g.launch().map_err(|e| device("graph launch")(format!("{e:?}"))),
            None => Err(ExecError::Device("the captured graph went missing".into())),
        }
    }

    fn forget_replays(&mut self) {
        self.graphs.clear();
    }

    fn sync(&mut self) -> Result<(), ExecError> {
        self.stream
            .synchronize()
            .map_err(|e| device("synchronize")(format!("{e:?}")))
    }

    fn bytes(&self) -> usize {
        self.bytes
    }

    fn bf16(&self) -> bool {
        self.bf16
    }

    fn flash(&self, dh: usize) -> bool {
        self.flash.is_some() && (dh == 32 || dh == 64)
    }
}

impl Drop for CudaExec {
    fn drop(&mut self) {
        self.forget_graphs();
        // SAFETY: the handle was made by `new` and is not used after this; the allocations are this
        // executor's own, and the stream (synchronised above) no longer uses them.
        unsafe {
            let _ = blas::destroy_handle(self.blas);
            for a in self.allocs.drain(..).filter(|a| a.ptr != 0) {
                let _ = result::free_sync(a.ptr);
            }
        }
    }
}

/// `data` as `W` bytes each, written by `put`; large slices on several threads (a model's weights are
/// converted once at start-up, hundreds of millions of values for the `paper` sizes).
fn le_bytes<T: Copy + Sync, const W: usize>(data: &[T], put: impl Fn(T, &mut [u8; W]) + Sync) -> Vec<u8> {
    const CHUNK: usize = 1 << 20;
    let mut out = vec![0u8; data.len() * W];
    let fill = |src: &[T], dst: &mut [u8]| {
        for (x, o) in src.iter().zip(dst.chunks_exact_mut(W)) {
            if let Ok(o) = <&mut [u8; W]>::try_from(o) {
                put(*x, o);
            }
        }
    };
    if data.len() <= CHUNK {
        fill(data, &mut out);
        return out;
    }
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(16);
    let per = data.len().div_ceil(threads).max(CHUNK);
    std::thread::scope(|s| {
        for (src, dst) in data.chunks(per).zip(out.chunks_mut(per * W)) {
            s.spawn(|| fill(src, dst));
        }
    });
    out
}

/// `x` as bf16 bits, to nearest with ties to even (NaN stays NaN), as `bf16.cuh`'s `to_bf16`.
pub fn bf16_bits(x: f32) -> u16 {
    let u = x.to_bits();
    if u & 0x7fff_ffff > 0x7f80_0000 {
        return ((u >> 16) | 0x40) as u16;
    }
    (u.wrapping_add(0x7fff + ((u >> 16) & 1)) >> 16) as u16
}
