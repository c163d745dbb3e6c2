//! An NCCL communicator usable from any thread (one at a time), its stream, and the collectives queued
//! on that stream by raw device address.
#![allow(unsafe_code)]

use cudarc::driver::CudaStream;
use cudarc::nccl::{result, sys};
use std::sync::Arc;

/// The communicator and the stream its collectives run on.
pub(crate) struct Comm {
    raw: sys::ncclComm_t,
    pub(crate) stream: Arc<CudaStream>,
}

// SAFETY: an NCCL communicator may be used from any thread as long as calls on it do not overlap; the
// group serialises them (its own calls on the training thread, started ones on cubecl's device thread,
// which the training thread reaches only after burn-fusion has run everything queued before).
unsafe impl Send for Comm {}
// SAFETY: as above.
unsafe impl Sync for Comm {}

impl Comm {
    /// Joins the communicator of `world` ranks identified by `id`, as `rank`, on `stream`'s context
    /// (bound to this thread).
    pub(crate) fn join(
        id: [u8; 128],
        rank: usize,
        world: usize,
        stream: Arc<CudaStream>,
    ) -> Result<Self, String> {
        stream
            .context()
            .bind_to_thread()
            .map_err(|e| format!("binding the context: {e:?}"))?;
        let id = sys::ncclUniqueId {
            internal: id.map(|b| b as std::ffi::c_char),
        };
        let (rank, world) = (
            i32::try_from(rank).map_err(|_| format!("rank {rank}"))?,
            i32::try_from(world).map_err(|_| format!("world size {world}"))?,
        );
        let mut raw = std::ptr::null_mut();
        // SAFETY: `raw` receives the communicator; the id comes from rank 0's `ncclGetUniqueId`.
        unsafe { result::comm_init_rank(&mut raw, world, id, rank) }.map_err(|e| format!("{e:?}"))?;
        Ok(Self { raw, stream })
    }

    fn cu_stream(&self) -> sys::cudaStream_t {
        self.stream.cu_stream() as sys::cudaStream_t
    }

    /// Queues `out = op(in)` over ranks of `n` floats.
    ///
    /// # Safety
    /// `input` and `output` must be device buffers of at least `n` floats that stay alive, and are not
    /// written by anything else, until the stream has passed the collective.
    pub(crate) unsafe fn all_reduce(
        &self,
        input: u64,
        output: u64,
        n: usize,
        op: sys::ncclRedOp_t,
    ) -> Result<(), String> {
        // SAFETY: the caller's contract; the communicator lives as long as `self`.
        unsafe {
            result::all_reduce(
                input as *const _,
                output as *mut _,
                n,
                sys::ncclDataType_t::ncclFloat32,
                op,
                self.raw,
                self.cu_stream(),
            )
        }
        .map(|_| ())
        .map_err(|e| format!("all-reduce: {e:?}"))
    }

    /// Queues rank `root`'s `n` floats of `input` into every rank's `output`.
    ///
    /// # Safety
    /// As [`Comm::all_reduce`].
    pub(crate) unsafe fn broadcast(
        &self,
        input: u64,
        output: u64,
        n: usize,
        root: usize,
    ) -> Result<(), String> {
        let root = i32::try_from(root).map_err(|_| format!("broadcast root {root}"))?;
        // SAFETY: the caller's contract.
        unsafe {
            result::broadcast(
                input as *const _,
                output as *mut _,
                n,
                sys::ncclDataType_t::ncclFloat32,
                root,
                self.raw,
                self.cu_stream(),
            )
        }
        .map(|_| ())
        .map_err(|e| format!("broadcast: {e:?}"))
    }
}

impl Drop for Comm {
    fn drop(&mut self) {
        // SAFETY: the communicator is live and used by nothing after this.
        let _ = unsafe { result::comm_destroy(self.raw) };
    }
}
