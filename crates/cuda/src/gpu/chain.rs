//! A captured sequence's runs of products and few-query attentions as one persistent kernel
//! (`kernels/chain.cu`): the tasks laid out in device memory once, when the sequence is captured, and one
//! cooperative launch in the graph where there were as many launches as tasks.

use super::params::{AttendRows, Gemv};
use super::{CudaExec, device};
use crate::ops::{ExecError, Op};
use cudarc::driver::{DeviceRepr, result, sys};
use std::ffi::c_void;

/// `struct Chain` of `chain.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Chain {
    tasks: u64,
    bar: u64,
    count: i32,
    task_bytes: i32,
}

// SAFETY: a plain `#[repr(C)]` struct of integers, laid out as the kernel's struct.
unsafe impl DeviceRepr for Chain {}

/// `CHAIN_GEMV` and `CHAIN_ATTEND` of `chain.cu`.
const GEMV: i32 = 0;
const ATTEND: i32 = 1;

/// `sizeof(ChainTask)`: the kind, four bytes of padding, then the larger of the two parameter structs (both
/// end on an 8-byte boundary, so the union has no tail of its own).
const TASK_BYTES: usize = 8 + max(size_of::<Gemv>(), size_of::<AttendRows>());

const fn max(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

// Both structs are whole 8-byte words of fields (no padding bytes), so their bytes may be copied.
const _: () = assert!(size_of::<Gemv>() == 16 * 8 + 8 + 12 * 4);
const _: () = assert!(size_of::<AttendRows>() == 7 * 8 + 7 * 8 + 8 * 4);

/// The bytes of `p`, a `#[repr(C)]` parameter struct without padding bytes.
fn bytes_of<T: DeviceRepr>(p: &T) -> &[u8] {
    // SAFETY: `T` is one of the parameter structs asserted above to have no padding, so every byte of it
    // is initialised; the slice borrows `p`.
    unsafe { std::slice::from_raw_parts((p as *const T).cast::<u8>(), size_of::<T>()) }
}

/// What a captured sequence launches: an operation of its own, or a chain's tasks (device address, count).
pub(super) enum Launch<'a> {
    One(&'a Op),
    Chain(u64, usize),
}

/// Whether `op` can be a task of a chain.
fn chainable(op: &Op) -> bool {
    matches!(op, Op::Gemv(_) | Op::AttendRows(_))
}

impl CudaExec {
    /// `ops` as launches: each run of at least two products and attentions a chain whose tasks are uploaded
    /// now (their addresses added to `owned`, freed with the graph), the rest one by one.
    pub(super) fn plan<'a>(&self, ops: &'a [Op], owned: &mut Vec<u64>) -> Result<Vec<Launch<'a>>, ExecError> {
        let mut out = Vec::with_capacity(ops.len());
        let mut i = 0;
        while i < ops.len() {
            let run = ops[i..].iter().take_while(|op| chainable(op)).count();
            if self.chain_blocks == 0 || run < 2 {
                out.push(Launch::One(&ops[i]));
                i += 1;
                continue;
            }
            let mut bytes = vec![0u8; run * TASK_BYTES];
            for (op, task) in ops[i..i + run].iter().zip(bytes.chunks_exact_mut(TASK_BYTES)) {
                let (kind, params) = match op {
                    Op::Gemv(g) => (GEMV, bytes_of(&self.gemv(g)).to_vec()),
                    Op::AttendRows(a) => (ATTEND, bytes_of(&self.attend_rows(a)).to_vec()),
                    _ => {
                        return Err(ExecError::Invalid(
                            "a chain took an operation it cannot run".into(),
                        ));
                    }
                };
                task[..4].copy_from_slice(&kind.to_le_bytes());
                task[8..8 + params.len()].copy_from_slice(&params);
            }
            self.ctx
                .bind_to_thread()
                .map_err(|e| device("binding the context")(format!("{e:?}")))?;
            // SAFETY: a plain allocation of the bound context, filled before any launch reads it; `owned`
            // frees it when the graph that names it goes.
            let ptr = unsafe { result::malloc_sync(bytes.len()) }
                .map_err(|e| device("cuMemAlloc (a chain's tasks)")(format!("{e:?}")))?;
            owned.push(ptr);
            // SAFETY: `ptr` holds `bytes.len()` bytes; the copy finishes before the call returns.
            unsafe { result::memcpy_htod_sync(ptr, &bytes) }
                .map_err(|e| device("a chain's tasks to the device")(format!("{e:?}")))?;
            out.push(Launch::Chain(ptr, run));
            i += run;
        }
        Ok(out)
    }

    /// Launches the chain of `count` tasks at `tasks` on `chain_blocks` blocks, all resident at once.
    pub(super) fn launch_chain(&self, tasks: u64, count: usize) -> Result<(), ExecError> {
        let name = "umgen_chain";
        let f = self
            .functions
            .get(name)
            .ok_or_else(|| ExecError::Device(format!("kernel {name} was not compiled")))?;
        let params = Chain {
            tasks,
            bar: self.chain_barrier,
            count: i32::try_from(count)
                .map_err(|_| ExecError::Invalid("a chain of too many tasks".into()))?,
            task_bytes: TASK_BYTES as i32,
        };
        // A cooperative launch: the driver refuses a grid that cannot be resident at once, which the grid
        // barrier needs (a block waiting for one that never starts would wait forever).
        // SAFETY: a zeroed union is a valid value for its integer members; the one set is the attribute's.
        let mut value: sys::CUlaunchAttributeValue = unsafe { std::mem::zeroed() };
        value.cooperative = 1;
        let mut attribute = sys::CUlaunchAttribute {
            id: sys::CUlaunchAttributeID::CU_LAUNCH_ATTRIBUTE_COOPERATIVE,
            pad: [0; 4],
            value,
        };
        let config = sys::CUlaunchConfig {
            gridDimX: self.chain_blocks,
            gridDimY: 1,
            gridDimZ: 1,
            blockDimX: 256,
            blockDimY: 1,
            blockDimZ: 1,
            sharedMemBytes: 0,
            hStream: self.stream.cu_stream(),
            attrs: &mut attribute,
            // `UMGEN_CHAIN_COOPERATIVE=0`: a plain launch, for drivers that refuse a cooperative one in a
            // capture; the grid is sized to be resident at once all the same.
            numAttrs: u32::from(std::env::var("UMGEN_CHAIN_COOPERATIVE").map_or(true, |v| v != "0")),
        };
        let mut args = [(&params as *const Chain).cast_mut().cast::<c_void>()];
        // SAFETY: every task was checked as its operation before the capture and laid out as the kernel's
        // `ChainTask` (it traps on another size); the barrier's two words are this executor's, zero
        // between launches; `params` outlives the call (the driver copies it).
        unsafe { sys::cuLaunchKernelEx(&config, f.cu_function(), args.as_mut_ptr(), std::ptr::null_mut()) }
            .result()
            .map_err(|e| device(name)(format!("{e:?}")))
    }
}
