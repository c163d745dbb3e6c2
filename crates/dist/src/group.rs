//! The [`ProcessGroup`] trait and its TCP implementation.

use crate::error::{DistError, Result};
use crate::session::Session;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorData};
use std::sync::Arc;

/// What every process group offers, whatever the tensors' backend.
pub trait Group {
    /// This rank.
    fn rank(&self) -> usize;
    /// Number of ranks.
    fn world_size(&self) -> usize;
    /// Returns when every rank has called it.
    fn barrier(&mut self) -> Result<()>;
    /// Ends cleanly (after a final barrier), so that no rank takes another's exit for a crash.
    fn finish(&mut self);
    /// The backend's name, for logs (`single`, `tcp`, `nccl`).
    fn backend(&self) -> &'static str;
}

/// Collectives over all ranks of a job, on flat `f32` tensors of backend `B`. Every rank must call the
/// same collectives in the same order with tensors of the same length.
pub trait ProcessGroup<B: Backend>: Group {
    /// The element-wise mean over ranks; every rank receives bit-identical values.
    fn all_reduce_mean(&mut self, t: Tensor<B, 1>) -> Result<Tensor<B, 1>>;
    /// Rank `root`'s values, on every rank (the others' values only give the length).
    fn broadcast(&mut self, t: Tensor<B, 1>, root: usize) -> Result<Tensor<B, 1>>;
    /// A handle that starts collectives without waiting, where this group has one (NCCL); `None` where
    /// each collective completes before it returns (TCP, a single rank).
    fn async_collective(&self) -> Option<Arc<dyn AsyncCollective<B>>> {
        None
    }
}

/// Collectives that start without the host waiting for the device: each is queued behind the work that
/// produces its input and runs beside the work queued after it. They take a backend's tensors of any
/// shape as they lie (primitives: no reshape to queue for each), packed `f32`. Every rank must start the
/// same collectives in the same order with tensors of the same shapes.
pub trait AsyncCollective<B: Backend>: Send + Sync {
    /// Starts the element-wise mean over ranks of each tensor of a bucket, as one launch. The results
    /// may be read only through what [`AsyncCollective::settle`] returns for them.
    fn start_mean(&self, bucket: Vec<FloatTensor<B>>) -> Result<Vec<FloatTensor<B>>>;
    /// Starts, as one launch, the copy of each tensor of a bucket from its rank in `roots` (one per
    /// tensor) to every rank; read the results as those of [`AsyncCollective::start_mean`].
    fn start_broadcast(&self, bucket: Vec<FloatTensor<B>>, roots: &[usize]) -> Result<Vec<FloatTensor<B>>>;
    /// The results of started collectives, ordered so that whatever reads them runs after the
    /// collectives (and the failure of any started collective).
    fn settle(&self, started: Vec<FloatTensor<B>>) -> Result<Vec<FloatTensor<B>>>;
}

/// The group of a lone process: every collective is the identity.
#[derive(Debug, Clone, Copy, Default)]
pub struct Single;

impl Group for Single {
    fn rank(&self) -> usize {
        0
    }
    fn world_size(&self) -> usize {
        1
    }
    fn barrier(&mut self) -> Result<()> {
        Ok(())
    }
    fn finish(&mut self) {}
    fn backend(&self) -> &'static str {
        "single"
    }
}

impl<B: Backend> ProcessGroup<B> for Single {
    fn all_reduce_mean(&mut self, t: Tensor<B, 1>) -> Result<Tensor<B, 1>> {
        Ok(t)
    }
    fn broadcast(&mut self, t: Tensor<B, 1>, _root: usize) -> Result<Tensor<B, 1>> {
        Ok(t)
    }
}

/// Collectives through host memory over the session's TCP ring: for CPU runs and tests, and for GPUs
/// without NCCL.
#[derive(Debug)]
pub struct TcpGroup {
    session: Session,
}

impl TcpGroup {
    /// Over a connected session.
    pub fn new(session: Session) -> Self {
        Self { session }
    }

    /// Runs `f` on the ring as collective `op`, counted by the watchdog; a failure names the watchdog's
    /// reason when it has one (the peer that died), else the socket error.
    fn collective(
        &mut self,
        op: &'static str,
        buf: &mut [f32],
        f: impl FnOnce(&mut crate::ring::Ring, &mut [f32]) -> std::io::Result<()>,
    ) -> Result<()> {
        let rank = self.session.rank();
        let Some(ring) = self.session.ring.as_mut() else {
            return Ok(());
        };
        // A moment for the watchdog to learn why a socket broke.
        let grace = std::time::Duration::from_millis(200);
        crate::watchdog::Watchdog::track(self.session.watchdog.as_ref(), rank, op, grace, || {
            f(ring, buf).map_err(|e| DistError::Collective {
                rank,
                op,
                reason: format!("{e} (a peer exited or stalled?)"),
            })
        })
    }

    /// Sums `buf` over ranks in place (host memory).
    pub fn all_reduce_sum_host(&mut self, buf: &mut [f32]) -> Result<()> {
        self.collective("all-reduce", buf, |r, b| r.all_reduce_sum(b))
    }
}

/// An error naming `root` unless it is one of the `world` ranks (a broadcast's source).
pub(crate) fn root_in_range(root: usize, rank: usize, world: usize) -> Result<()> {
    match root < world {
        true => Ok(()),
        false => Err(DistError::Collective {
            rank,
            op: "broadcast",
            reason: format!("root {root} of {world} ranks"),
        }),
    }
}

fn to_host<B: Backend>(t: Tensor<B, 1>, rank: usize, op: &'static str) -> Result<Vec<f32>> {
    t.into_data()
        .convert::<f32>()
        .into_vec::<f32>()
        .map_err(|e| DistError::Collective {
            rank,
            op,
            reason: format!("reading the tensor: {e:?}"),
        })
}

impl Group for TcpGroup {
    fn rank(&self) -> usize {
        self.session.rank()
    }
    fn world_size(&self) -> usize {
        self.session.world_size()
    }
    fn barrier(&mut self) -> Result<()> {
        self.collective("barrier", &mut [0.0], |r, b| r.all_reduce_sum(b))
    }
    fn finish(&mut self) {
        if let Some(d) = &self.session.watchdog {
            d.finish();
        }
    }
    fn backend(&self) -> &'static str {
        "tcp"
    }
}

impl<B: Backend> ProcessGroup<B> for TcpGroup {
    fn all_reduce_mean(&mut self, t: Tensor<B, 1>) -> Result<Tensor<B, 1>> {
        let device = t.device();
        let mut v = to_host(t, self.session.rank(), "all-reduce")?;
        self.all_reduce_sum_host(&mut v)?;
        let scale = 1.0 / self.session.world_size() as f32;
        v.iter_mut().for_each(|x| *x *= scale);
        let n = v.len();
        Ok(Tensor::from_data(TensorData::new(v, [n]), &device))
    }
    fn broadcast(&mut self, t: Tensor<B, 1>, root: usize) -> Result<Tensor<B, 1>> {
        let device = t.device();
        let rank = self.session.rank();
        root_in_range(root, rank, self.session.world_size())?;
        let mut v = to_host(t, rank, "broadcast")?;
        self.collective("broadcast", &mut v, |r, b| r.broadcast(b, root))?;
        let n = v.len();
        Ok(Tensor::from_data(TensorData::new(v, [n]), &device))
    }
}
