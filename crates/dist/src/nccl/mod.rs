//! NCCL collectives on the device memory of burn-cuda tensors (feature `cuda`).
//!
//! Two ways to run one. The group's own collectives (`all_reduce_mean`, `broadcast`, `barrier`) order
//! work on the host: they resolve the fusion tensor (running the queued kernels that produce it), wait for
//! cubecl's stream (`client.sync()`), run the NCCL call on the group's stream and wait for it before burn
//! touches the result; they serve the occasional small exchange (losses, flags, the first broadcast).
//! Gradients, and the parameters a sharded optimizer updates, go through [`AsyncCollective`]
//! (`started.rs`): queued in cubecl's stream order and ordered with the NCCL stream by CUDA events, with
//! no host wait. Collectives are out of place into a freshly allocated tensor, so NCCL never writes into
//! a buffer that autodiff may share between gradients.
#![allow(unsafe_code)]

mod comm;
mod started;

use crate::error::{DistError, Result};
use crate::group::{AsyncCollective, Group, ProcessGroup};
use crate::session::Session;
use crate::watchdog::Watchdog;
use burn::backend::Cuda;
use burn::backend::cuda::CudaDevice;
use burn::tensor::{Tensor, TensorPrimitive};
use burn_cubecl::CubeBackend;
use burn_cubecl::tensor::CubeTensor;
use comm::Comm;
use cudarc::driver::{CudaContext, CudaSlice, DevicePtr};
use cudarc::nccl::Id;
use cudarc::nccl::sys::ncclRedOp_t;
use started::Shared;
use std::sync::Arc;

type Inner = CubeBackend<burn::cubecl::cuda::CudaRuntime, f32, i32, u8>;

/// A fresh NCCL unique id (rank 0 makes it; the rendezvous hands it to the others).
pub fn nccl_id(rank: usize) -> Result<Vec<u8>> {
    let id = Id::new().map_err(|e| DistError::Nccl {
        rank,
        reason: format!("creating the unique id: {e:?} (is libnccl.so on LD_LIBRARY_PATH?)"),
    })?;
    Ok(id.internal().iter().map(|c| *c as u8).collect())
}

/// Collectives through NCCL on one GPU per rank.
pub struct NcclGroup {
    session: Session,
    shared: Arc<Shared>,
    device: CudaDevice,
    /// One float for barriers.
    token: CudaSlice<f32>,
}

impl std::fmt::Debug for NcclGroup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NcclGroup")
            .field("rank", &self.session.rank())
            .field("world_size", &self.session.world_size())
            .field("device", &self.device)
            .finish()
    }
}

/// The device pointer and element count of a resolved, contiguous f32 tensor.
fn raw(t: Tensor<Cuda, 1>, rank: usize) -> Result<(CubeTensor<burn::cubecl::cuda::CudaRuntime>, u64, usize)> {
    let n = t.dims()[0];
    let fusion = match t.into_primitive() {
        TensorPrimitive::Float(f) => f,
        TensorPrimitive::QFloat(_) => {
            return Err(DistError::Nccl {
                rank,
                reason: "quantized tensors cannot be reduced".into(),
            });
        }
    };
    let mut c: CubeTensor<_> = fusion.client.clone().resolve_tensor_float::<Inner>(fusion);
    if !c.is_contiguous() {
        c = burn_cubecl::kernel::into_contiguous(c);
    }
    let err = |e: String| DistError::Nccl { rank, reason: e };
    let res = c
        .client
        .get_resource(c.handle.clone())
        .map_err(|e| err(format!("device buffer: {e:?}")))?;
    let (ptr, bytes) = (res.resource().ptr, res.resource().size);
    if bytes < 4 * n as u64 {
        return Err(err(format!("buffer of {bytes} bytes for {n} floats")));
    }
    burn::cubecl::future::block_on(c.client.sync()).map_err(|e| err(format!("sync: {e:?}")))?;
    Ok((c, ptr, n))
}

impl NcclGroup {
    /// Builds the communicator on `device` (the GPU of `LOCAL_RANK`) from the session's NCCL id.
    pub fn new(session: Session, device: &CudaDevice) -> Result<Self> {
        let rank = session.rank();
        let err = |what: &str, e: String| DistError::Nccl {
            rank,
            reason: format!("{what}: {e}"),
        };
        let bytes: [u8; 128] = session
            .payload
            .as_slice()
            .try_into()
            .map_err(|_| err("unique id", format!("{} bytes, not 128", session.payload.len())))?;
        // The primary context, which cubecl uses too.
        let ctx = CudaContext::new(device.index).map_err(|e| err("CUDA context", format!("{e:?}")))?;
        let stream = ctx.new_stream().map_err(|e| err("stream", format!("{e:?}")))?;
        let comm = Comm::join(bytes, rank, session.world_size(), stream.clone())
            .map_err(|e| err("communicator", e))?;
        let token = stream
            .alloc_zeros::<f32>(1)
            .map_err(|e| err("alloc", format!("{e:?}")))?;
        Ok(Self {
            session,
            shared: Arc::new(Shared::new(comm, rank)),
            device: device.clone(),
            token,
        })
    }

    fn counted<T>(&mut self, op: &'static str, f: impl FnOnce(&mut Self) -> Result<T>) -> Result<T> {
        let (rank, dog) = (self.session.rank(), self.session.watchdog.clone());
        Watchdog::track(dog.as_ref(), rank, op, std::time::Duration::ZERO, || f(self))
    }

    /// Runs `call(comm, input, output, n)` out of place into a fresh tensor and waits for it.
    fn out_of_place(
        &mut self,
        t: Tensor<Cuda, 1>,
        call: impl FnOnce(&Comm, u64, u64, usize) -> std::result::Result<(), String>,
    ) -> Result<Tensor<Cuda, 1>> {
        let rank = self.session.rank();
        let n = t.dims()[0];
        let out = Tensor::<Cuda, 1>::empty([n], &self.device);
        // Resolving the input runs burn-fusion's queue, started collectives included, so this one is
        // queued after them on every rank.
        let (_keep_in, in_ptr, _) = raw(t, rank)?;
        let (_keep_out, out_ptr, _) = raw(out.clone(), rank)?;
        self.shared.check()?;
        let comm = &self.shared.comm;
        // The two buffers are live burn buffers of at least `n` floats (checked in `raw`), kept alive
        // until the stream is synchronised below.
        let result = call(comm, in_ptr, out_ptr, n);
        let synced = comm.stream.synchronize();
        result.map_err(|reason| DistError::Nccl { rank, reason })?;
        synced.map_err(|e| DistError::Nccl {
            rank,
            reason: format!("stream: {e:?}"),
        })?;
        Ok(out)
    }
}

impl Group for NcclGroup {
    fn rank(&self) -> usize {
        self.session.rank()
    }
    fn world_size(&self) -> usize {
        self.session.world_size()
    }
    fn barrier(&mut self) -> Result<()> {
        self.counted("barrier", |g| {
            let rank = g.session.rank();
            g.shared.check()?;
            let comm = &g.shared.comm;
            let (ptr, _record) = g.token.device_ptr(&comm.stream);
            // SAFETY: the group's own one-float buffer, alive as long as the group.
            unsafe { comm.all_reduce(ptr, ptr, 1, ncclRedOp_t::ncclSum) }
                .map_err(|reason| DistError::Nccl { rank, reason })?;
            comm.stream.synchronize().map_err(|e| DistError::Nccl {
                rank,
                reason: format!("{e:?}"),
            })
        })
    }
    fn finish(&mut self) {
        if let Some(d) = &self.session.watchdog {
            d.finish();
        }
    }
    fn backend(&self) -> &'static str {
        "nccl"
    }
}

impl ProcessGroup<Cuda> for NcclGroup {
    fn async_collective(&self) -> Option<Arc<dyn AsyncCollective<Cuda>>> {
        umgen_ops::external::AVAILABLE
            .then(|| Arc::new(self.shared.clone()) as Arc<dyn AsyncCollective<Cuda>>)
    }
    fn all_reduce_mean(&mut self, t: Tensor<Cuda, 1>) -> Result<Tensor<Cuda, 1>> {
        self.counted("all-reduce", |g| {
            // SAFETY: `out_of_place` passes live buffers of `n` floats.
            g.out_of_place(t, |comm, i, o, n| unsafe {
                comm.all_reduce(i, o, n, ncclRedOp_t::ncclAvg)
            })
        })
    }
    fn broadcast(&mut self, t: Tensor<Cuda, 1>, root: usize) -> Result<Tensor<Cuda, 1>> {
        crate::group::root_in_range(root, self.session.rank(), self.session.world_size())?;
        self.counted("broadcast", |g| {
            // SAFETY: as above.
            g.out_of_place(t, |comm, i, o, n| unsafe { comm.broadcast(i, o, n, root) })
        })
    }
}
