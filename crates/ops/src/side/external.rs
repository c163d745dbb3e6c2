//! Work of another library (NCCL's collectives) in cubecl's stream order, for burn-cuda tensors: a custom
//! operation on burn-fusion's stream that, when it runs, hands the work cubecl's CUDA stream at that
//! point and its operands' device memory. The work may queue on that stream, or on a stream of its own
//! ordered by CUDA events (recorded on cubecl's stream, waited on by its own, and the other way round).

use super::fusion::{Handles, Inner, Primitive, empty_f32, register_many};
use super::{on_device_thread, pointer};
use crate::kernels::LaunchThread;
use burn::backend::Cuda;
use burn::tensor::TensorMetadata;
use burn::tensor::ops::FloatTensor;
use burn_ir::CustomOpIr;

/// Whether this build can hand external work cubecl's stream (the vendored cubecl-cuda's `last_stream`,
/// the `patched-cubecl` feature).
pub const AVAILABLE: bool = cfg!(feature = "patched-cubecl");

/// A tensor's device memory as external work sees it: the address of its first `f32`, the count, and what
/// keeps the buffer alive (clone it to keep it past the work's return, e.g. until another stream is done
/// with it).
#[derive(Clone)]
pub struct Buffer {
    /// Device address.
    pub ptr: u64,
    /// Number of `f32` elements.
    pub len: usize,
    _keep: Primitive,
}

impl std::fmt::Debug for Buffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Buffer({:#x}, {})", self.ptr, self.len)
    }
}

/// Work queued from cubecl's device thread.
pub trait External: Send + Sync + std::fmt::Debug + 'static {
    /// Queues the work: everything queued on `stream` before this (a `CUstream` of the device's primary
    /// context, current on this thread) produces `inputs`; everything queued on it after reads `outputs`.
    fn queue(&self, stream: usize, inputs: &[Buffer], outputs: &[Buffer]) -> Result<(), String>;
    /// Whether `queue` reads its buffers; work that only orders streams says no, and gets none (its
    /// first input still places it on cubecl's stream).
    fn buffers(&self) -> bool {
        true
    }
    /// The operation could not run `queue` (or `queue` failed) for `why`: the outputs hold no result.
    fn failed(&self, why: String);
}

/// What an external operation outputs.
#[derive(Debug, Clone)]
pub enum Outputs {
    /// Fresh packed `f32` tensors of the inputs' shapes.
    Like,
    /// The inputs themselves (work that only orders streams).
    Inputs,
}

#[derive(Debug)]
struct Pass<W> {
    outputs: Outputs,
    work: W,
}

/// Device buffers of packed `f32` tensors, each kept alive.
fn buffers(ts: &[Primitive]) -> Result<Vec<Buffer>, String> {
    ts.iter()
        .map(|t| {
            let (ptr, _) = pointer(t)?;
            Ok(Buffer {
                ptr,
                len: t.meta.shape().iter().product(),
                _keep: t.clone(),
            })
        })
        .collect()
}

impl<W: External> super::fusion::SidePass for Pass<W> {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let inputs: Vec<Primitive> = desc
            .inputs
            .iter()
            .map(|t| burn_cubecl::kernel::into_contiguous(handles.get_float_tensor::<Inner>(t)))
            .collect();
        // `external` registers no operation without inputs.
        let Some(like) = inputs.first().cloned() else {
            self.work.failed("an external operation without inputs".into());
            return Vec::new();
        };
        let outputs: Vec<Primitive> = match &self.outputs {
            Outputs::Inputs => inputs.clone(),
            Outputs::Like => inputs
                .iter()
                .map(|t| empty_f32(&like, t.meta.shape().iter().copied().collect()))
                .collect(),
        };
        let (ins, outs, probe) = (inputs, outputs.clone(), like.clone());
        let work = &self.work;
        let ran = on_device_thread(&like, LaunchThread::Device, move || {
            let (ins, outs) = match work.buffers() {
                true => (buffers(&ins)?, buffers(&outs)?),
                false => {
                    // Fetching one pointer resolves cubecl's stream for the caller.
                    pointer(&probe)?;
                    (Vec::new(), Vec::new())
                }
            };
            let stream = current_stream()?;
            work.queue(stream, &ins, &outs)
        });
        if let Err(why) = ran {
            self.work.failed(why);
        }
        outputs
    }
}

/// cubecl's stream for the caller, right after its operands' pointers were fetched.
fn current_stream() -> Result<usize, String> {
    #[cfg(feature = "patched-cubecl")]
    {
        let s = burn::cubecl::cuda::last_stream();
        if s.is_null() {
            return Err("no cubecl stream resolved on this thread".into());
        }
        Ok(s as usize)
    }
    #[cfg(not(feature = "patched-cubecl"))]
    Err("built against an unpatched cubecl-cuda (no `last_stream`; vendor/README.md)".into())
}

/// Registers `work` on burn-fusion's stream with `inputs` (tensors of any shape, at least one) and
/// returns its outputs; the work runs when burn-fusion reaches it ([`External::queue`]). Without inputs
/// nothing is registered: the work is told it failed and there are no outputs.
pub fn external<W: External>(
    id: &'static str,
    inputs: Vec<FloatTensor<Cuda>>,
    outputs: Outputs,
    work: W,
) -> Vec<FloatTensor<Cuda>> {
    if inputs.is_empty() {
        work.failed(format!("{id}: an external operation without inputs"));
        return Vec::new();
    }
    // Either kind of output has the inputs' shapes.
    let shapes: Vec<Vec<usize>> = inputs
        .iter()
        .map(|t| t.shape().iter().copied().collect())
        .collect();
    register_many(id, inputs, shapes, Pass { outputs, work })
}
