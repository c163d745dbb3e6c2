//! Collectives that start without the host waiting ([`AsyncCollective`] for NCCL): each is an external
//! operation on burn-fusion's stream (`umgen_ops::external`) that, where cubecl's stream has queued the
//! bucket's producers, records an event there, makes the NCCL stream wait for it, queues the bucket's
//! all-reduces (gradients) or broadcasts (a sharded optimizer's parameters) and records their end.
//! Settling makes cubecl's stream wait for those ends, so the backward pass's kernels queued between a
//! start and the settle run beside the collective.
#![allow(unsafe_code)]

use super::comm::Comm;
use crate::error::{DistError, Result};
use crate::group::AsyncCollective;
use burn::backend::Cuda;
use burn::tensor::TensorMetadata;
use burn::tensor::ops::FloatTensor;
use cudarc::driver::{result as cu, sys as cus};
use cudarc::nccl::{result as nccl_result, sys};
use std::sync::{Arc, Mutex};
use umgen_ops::external::{Buffer, External, Outputs, external};

/// A started bucket: the event at its end and the buffers it reads and writes, kept alive until cubecl's
/// stream waits for it.
struct Pending {
    done: cus::CUevent,
    _keep: Vec<Buffer>,
}

// SAFETY: a CUDA event handle may be used from any thread.
unsafe impl Send for Pending {}

/// What the group and its started operations share.
pub(crate) struct Shared {
    pub(crate) comm: Comm,
    pub(crate) rank: usize,
    pending: Mutex<Vec<Pending>>,
    failure: Mutex<Option<String>>,
}

impl Shared {
    pub(crate) fn new(comm: Comm, rank: usize) -> Self {
        Self {
            comm,
            rank,
            pending: Mutex::new(Vec::new()),
            failure: Mutex::new(None),
        }
    }

    fn fail(&self, why: String) {
        if let Ok(mut f) = self.failure.lock() {
            f.get_or_insert(why);
        }
    }

    /// The first failure of a started operation, as an error.
    pub(crate) fn check(&self) -> Result<()> {
        let failed = self
            .failure
            .lock()
            .map(|f| f.clone())
            .unwrap_or_else(|_| Some("a started collective panicked".into()));
        match failed {
            Some(reason) => Err(DistError::Nccl {
                rank: self.rank,
                reason: format!("a started collective: {reason}"),
            }),
            None => Ok(()),
        }
    }
}

fn event() -> std::result::Result<cus::CUevent, String> {
    cu::event::create(cus::CUevent_flags::CU_EVENT_DISABLE_TIMING)
        .map_err(|e| format!("cuEventCreate: {e:?}"))
}

/// What a started bucket does to each of its tensors.
#[derive(Clone, Debug)]
enum Kind {
    /// The mean over ranks.
    Mean,
    /// The values of the rank given per tensor.
    Broadcast(Vec<usize>),
}

/// The collective of one bucket.
#[derive(Clone)]
struct Start(Arc<Shared>, Kind);

impl std::fmt::Debug for Start {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("NcclStart")
    }
}

impl External for Start {
    fn queue(&self, stream: usize, inputs: &[Buffer], outputs: &[Buffer]) -> std::result::Result<(), String> {
        let roots = match &self.1 {
            Kind::Broadcast(roots) if roots.len() != inputs.len() => {
                return Err(format!("{} roots for {} tensors", roots.len(), inputs.len()));
            }
            Kind::Broadcast(roots) => Some(roots),
            Kind::Mean => None,
        };
        if inputs.len() != outputs.len() || inputs.iter().zip(outputs).any(|(i, o)| i.len != o.len) {
            return Err(format!(
                "{} inputs into {} outputs of other lengths",
                inputs.len(),
                outputs.len()
            ));
        }
        let comm = &self.0.comm;
        let nccl = comm.stream.cu_stream();
        let ready = event()?;
        let done = event()?;
        // SAFETY: live events and streams of the current context; the buffers are kept alive in `pending`
        // until cubecl's stream has waited for `done`, and the outputs are fresh (nothing else writes them).
        unsafe {
            cu::event::record(ready, stream as cus::CUstream).map_err(|e| format!("cuEventRecord: {e:?}"))?;
            cu::stream::wait_event(nccl, ready, cus::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT)
                .map_err(|e| format!("cuStreamWaitEvent: {e:?}"))?;
            // Released once the wait has passed it.
            let _ = cu::event::destroy(ready);
            // One launch for the bucket's tensors.
            nccl_result::group_start().map_err(|e| format!("ncclGroupStart: {e:?}"))?;
            let reduced = inputs
                .iter()
                .zip(outputs)
                .enumerate()
                .try_for_each(|(k, (i, o))| match roots {
                    Some(roots) => comm.broadcast(i.ptr, o.ptr, i.len, roots[k]),
                    None => comm.all_reduce(i.ptr, o.ptr, i.len, sys::ncclRedOp_t::ncclAvg),
                });
            let ended = nccl_result::group_end().map_err(|e| format!("ncclGroupEnd: {e:?}"));
            reduced?;
            ended?;
            cu::event::record(done, nccl).map_err(|e| format!("cuEventRecord: {e:?}"))?;
        }
        self.0
            .pending
            .lock()
            .map_err(|_| "the pending collectives' lock is poisoned".to_string())?
            .push(Pending {
                done,
                _keep: inputs.iter().chain(outputs).cloned().collect(),
            });
        Ok(())
    }

    fn failed(&self, why: String) {
        self.0.fail(why);
    }
}

/// cubecl's stream waits for every started collective.
#[derive(Clone)]
struct Settle(Arc<Shared>);

impl std::fmt::Debug for Settle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("NcclSettle")
    }
}

impl External for Settle {
    fn buffers(&self) -> bool {
        false
    }

    fn queue(&self, stream: usize, _: &[Buffer], _: &[Buffer]) -> std::result::Result<(), String> {
        let pending = std::mem::take(
            &mut *self
                .0
                .pending
                .lock()
                .map_err(|_| "the pending collectives' lock is poisoned".to_string())?,
        );
        for p in pending {
            // SAFETY: a live event of this context, recorded on the NCCL stream; the buffers `p` keeps are
            // released only after the wait is queued, so cubecl reuses them after the collective.
            unsafe {
                cu::stream::wait_event(
                    stream as cus::CUstream,
                    p.done,
                    cus::CUevent_wait_flags::CU_EVENT_WAIT_DEFAULT,
                )
                .map_err(|e| format!("cuStreamWaitEvent: {e:?}"))?;
                let _ = cu::event::destroy(p.done);
            }
        }
        Ok(())
    }

    fn failed(&self, why: String) {
        self.0.fail(why);
    }
}

/// Queues `kind` on each tensor of `bucket` as one launch, into fresh tensors.
fn start(
    shared: &Arc<Shared>,
    name: &'static str,
    bucket: Vec<FloatTensor<Cuda>>,
    kind: Kind,
) -> Result<Vec<FloatTensor<Cuda>>> {
    shared.check()?;
    if bucket.is_empty() {
        return Ok(bucket);
    }
    if let Some(t) = bucket.iter().find(|t| t.dtype() != burn::tensor::DType::F32) {
        return Err(DistError::Nccl {
            rank: shared.rank,
            reason: format!("{name}: tensors are exchanged in f32, not {:?}", t.dtype()),
        });
    }
    Ok(external(name, bucket, Outputs::Like, Start(shared.clone(), kind)))
}

impl AsyncCollective<Cuda> for Arc<Shared> {
    fn start_mean(&self, bucket: Vec<FloatTensor<Cuda>>) -> Result<Vec<FloatTensor<Cuda>>> {
        start(self, "umgen_nccl_all_reduce", bucket, Kind::Mean)
    }

    fn start_broadcast(
        &self,
        bucket: Vec<FloatTensor<Cuda>>,
        roots: &[usize],
    ) -> Result<Vec<FloatTensor<Cuda>>> {
        start(
            self,
            "umgen_nccl_broadcast",
            bucket,
            Kind::Broadcast(roots.to_vec()),
        )
    }

    fn settle(&self, started: Vec<FloatTensor<Cuda>>) -> Result<Vec<FloatTensor<Cuda>>> {
        self.check()?;
        if started.is_empty() {
            return Ok(started);
        }
        Ok(external(
            "umgen_nccl_settle",
            started,
            Outputs::Inputs,
            Settle(self.clone()),
        ))
    }
}
