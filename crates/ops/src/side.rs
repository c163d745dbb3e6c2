//! A CUDA stream of umgen's own beside cubecl's, for work cubecl cannot launch (cuBLAS's products; umgen's
//! CUDA C kernels with `train.kernels.stream = "side"`), ordered with cubecl's stream on the device; and the
//! launch of umgen's CUDA C kernels on cubecl's own stream ([`cubecl_stream`], the default), which needs
//! no ordering at all.
//!
//! burn 0.21 gives no handle to cubecl's CUDA stream (each thread gets its own non-blocking stream), and
//! waiting on the host around every launch (as the NCCL group does) cost more than cuBLAS saved: the
//! `small` step took 708 ms against 650 ms on the cubek kernel (H100), the GPU idling while the host
//! caught up after each wait. So the two streams are ordered on the device, through two flags in device
//! memory and a counter `v` per piece of work:
//!
//! 1. cubecl's stream runs [`signal`], which stores `v` in flag 0 once everything queued before it is done;
//! 2. the side stream runs `umgen_wait` (one thread spinning until flag 0 is `v`), the work, then
//!    `umgen_store` (flag 1 = `v`, after a fence);
//! 3. cubecl's stream runs [`wait`], one thread spinning until flag 1 is `v`, so nothing queued after it
//!    (readers of the results, reuse of the operands' memory) starts before the work is done.
//!
//! The host never waits for the GPU (it waits for cubecl's device thread to have launched the signal). The
//! work is queued in the order the dependencies run, so even streams that share a hardware queue cannot
//! deadlock. The side streams showed a race this protocol does not explain: with the CUDA C kernels on
//! side streams, 14 of 15 same-seed one-step runs of `small-bundled` with burn's layer norm gave a wrong
//! gradient (a host wait after the cross-entropy's launches, [`waits`], hides it), and none of 30 with the
//! kernels on cubecl's stream (docs/decisions/004-cuda-kernels-on-cubecl-stream.md). Each user keeps one [`Side`] per thread and device:
//! cubecl gives each thread its own stream, and the protocol needs the two streams to take turns. (The
//! driver's stream memory operations, `cuStreamWaitValue32`, would spare the kernels on this side, but
//! refused cubecl's pool memory with `CUDA_ERROR_INVALID_VALUE` on an H100; the two small kernels are
//! compiled with NVRTC, which cubecl loads anyway.)
#![allow(unsafe_code)]

use crate::kernels::{KernelStream, Kernels as Choices, LaunchThread, SideFamily, SideSync};
use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::{DType, Shape};
use burn_cubecl::ops::numeric::zeros_client;
use cubecl::prelude::*;
pub(crate) use cubecl_stream::{
    launch as launch_on_cubecl, launch_bound as launch_bound_on_cubecl,
    launch_shared as launch_shared_on_cubecl,
};
use cudarc::driver::{CudaContext, CudaFunction, CudaStream, DeviceRepr, LaunchConfig, PushKernelArg};
use cudarc::nvrtc::{CompileOptions, compile_ptx_with_opts};
use std::cell::RefCell;
use std::sync::Arc;
use std::thread::LocalKey;

mod cubecl_stream;
pub mod external;
mod fusion;
mod waits;
pub(crate) use fusion::*;
use waits::foreign;
pub use waits::{device_thread_calls, foreign_streams};

/// Stores `value` in `flag[0]` (a single unit).
#[cube(launch)]
pub fn signal(flag: &mut Tensor<Atomic<u32>>, value: u32) {
    flag[0].store(value);
}

/// Spins (a single unit) until `flag[1]` holds `value`.
#[cube(launch)]
pub fn wait(flag: &mut Tensor<Atomic<u32>>, value: u32) {
    let mut seen = flag[1].load();
    while seen != value {
        seen = flag[1].load();
    }
}

/// The side stream's half of the protocol, in CUDA C for NVRTC.
const FLAG_KERNELS: &str = r#"
extern "C" __global__ void umgen_wait(unsigned int* flag, unsigned int v) {
    while (atomicAdd(flag, 0u) != v) {}
}
extern "C" __global__ void umgen_store(unsigned int* flag, unsigned int v) {
    __threadfence();
    atomicExch(flag, v);
}
"#;

/// A stream of the device's primary context and the two flags, for one device and the calling thread.
pub(crate) struct Side {
    ctx: Arc<CudaContext>,
    stream: Arc<CudaStream>,
    wait_fn: CudaFunction,
    store_fn: CudaFunction,
    flags: Primitive,
    flags_ptr: u64,
    /// The last piece of work's `v`.
    count: u32,
}

impl Side {
    /// A side stream on `like`'s device.
    pub(crate) fn new(like: &Primitive) -> Result<Self, String> {
        let device = like.device.index;
        // The primary context, which cubecl uses too, so burn's pointers are valid here.
        let ctx = CudaContext::new(device).map_err(|e| format!("CUDA context {device}: {e:?}"))?;
        ctx.bind_to_thread()
            .map_err(|e| format!("binding the context: {e:?}"))?;
        let stream = ctx.new_stream().map_err(|e| format!("stream: {e:?}"))?;
        let ptx = cudarc::nvrtc::compile_ptx(FLAG_KERNELS).map_err(|e| format!("NVRTC: {e:?}"))?;
        let module = ctx
            .load_module(ptx)
            .map_err(|e| format!("loading the flag kernels: {e:?}"))?;
        let function = |name: &str| {
            module
                .load_function(name)
                .map_err(|e| format!("kernel {name}: {e:?}"))
        };
        let (wait_fn, store_fn) = (function("umgen_wait")?, function("umgen_store")?);
        let flags = zeros_client(
            like.client.clone(),
            like.device.clone(),
            Shape::new([2]),
            DType::U32,
        );
        let (flags_ptr, _) = pointer(&flags)?;
        // The zeros are written by a kernel on cubecl's stream, which the side stream does not wait for: until
        // they land, the flags hold whatever the pool's memory held, and a stale 1 in flag 0 would let the
        // first piece of work start before its operands are written. Wait for them, once per side stream.
        burn::cubecl::future::block_on(like.client.sync())
            .map_err(|e| format!("zeroing the flags: {e:?}"))?;
        Ok(Self {
            ctx,
            stream,
            wait_fn,
            store_fn,
            flags,
            flags_ptr,
            count: 0,
        })
    }

    /// The device's primary context, bound to this thread by [`Side::new`] and [`Side::ordered`].
    pub(crate) fn context(&self) -> &Arc<CudaContext> {
        &self.ctx
    }

    /// The side stream (for libraries that take a stream, such as cuBLAS).
    pub(crate) fn stream(&self) -> &Arc<CudaStream> {
        &self.stream
    }

    /// Runs `work` of the kernel family `family` on the side stream between cubecl's queued work and what
    /// cubecl queues next, the host waiting around it as `sync` says for that family.
    pub(crate) fn ordered<T>(
        &mut self,
        (family, sync): (SideFamily, SideSync),
        work: impl FnOnce(&Arc<CudaStream>) -> Result<T, String>,
    ) -> Result<T, String> {
        self.ctx
            .bind_to_thread()
            .map_err(|e| format!("binding the context: {e:?}"))?;
        self.count = self.count.wrapping_add(1).max(1);
        let v = self.count;
        let client = &self.flags.client;
        let (sync_before, sync_after) = sync.waits(family);
        if sync_before {
            burn::cubecl::future::block_on(client.sync()).map_err(|e| format!("side sync: {e:?}"))?;
        }
        let one = || (CubeCount::Static(1, 1, 1), CubeDim::new_1d(1));
        let (count, dim) = one();
        signal::launch::<CudaRuntime>(client, count, dim, self.flags.clone().into_tensor_arg(), v);
        // Submitted before this side's wait, so that the GPU meets the two in dependency order: cubecl's device
        // thread answers a call only after the launches queued before it. (`client.flush()` would do
        // this too, but it also waits on the host for the previous flush's fence, so the host never runs more
        // than one side-stream launch ahead of the GPU: `small`'s step took 218–224 ms with it against 192 ms
        // with this call on one H100.)
        drop(
            client
                .get_resource(self.flags.handle.clone())
                .map_err(|e| format!("submitting the signal: {e:?}"))?,
        );
        let (flag0, flag1) = (self.flags_ptr, self.flags_ptr + 4);
        let single = LaunchConfig {
            grid_dim: (1, 1, 1),
            block_dim: (1, 1, 1),
            shared_mem_bytes: 0,
        };
        let stream = &self.stream;
        let run = |f: &CudaFunction, flag: u64, what: &str| {
            // SAFETY: `flags` (kept by `self`) holds two u32 at `flags_ptr`; the kernels take
            // `(unsigned int*, unsigned int)`.
            unsafe { stream.launch_builder(f).arg(&flag).arg(&v).launch(single) }
                .map(|_| ())
                .map_err(|e| format!("{what}: {e:?}"))
        };
        run(&self.wait_fn, flag0, "umgen_wait")?;
        // Flag 1 is stored even when the work fails, so that cubecl's stream is never left spinning.
        let done = work(stream);
        run(&self.store_fn, flag1, "umgen_store")?;
        if sync_after {
            stream.synchronize().map_err(|e| format!("side sync: {e:?}"))?;
        }
        let (count, dim) = one();
        wait::launch::<CudaRuntime>(client, count, dim, self.flags.clone().into_tensor_arg(), v);
        done
    }
}

/// The device pointer of `t`'s first element (cubecl's stream waits for `t`'s producer from here on), and
/// what keeps it alive.
pub(crate) fn pointer(t: &Primitive) -> Result<(u64, impl Sized + use<>), String> {
    let now = cubecl::stream_id::StreamId::current();
    if t.handle.stream != now {
        foreign(format_args!(
            "a {:?} buffer made on {} read from {now}",
            t.meta.shape(),
            t.handle.stream
        ));
    }
    let res = t
        .client
        .get_resource(t.handle.clone())
        .map_err(|e| format!("device buffer: {e:?}"))?;
    Ok((res.resource().ptr, res))
}

/// Runs `work` (a custom operation's launches and the device pointers they take) on cubecl's device
/// thread for `like`'s device, as one call the host waits for; an error if that thread cannot be reached.
/// With `thread` [`LaunchThread::Caller`] (`train.kernels.launch_thread = "caller"`) it runs `work` here.
///
/// Every call into cubecl that answers (a pointer fetch, `get_resource`) is a round trip to that thread,
/// which first runs everything queued before it: a cuBLAS product made five (four pointers and the
/// signal's submission), a kernel launch three to nine, each stopping the host until the device thread
/// caught up. Made on the device thread those calls run at once (cubecl runs calls from its own thread
/// inline), so a custom operation waits once. The work sees the caller's cubecl stream (cubecl's
/// `exclusive` carries it), and thread-local state it keeps lives on the device thread, keyed by that
/// stream ([`with_cached`]).
pub(crate) fn on_device_thread<T: Send + 'static>(
    like: &Primitive,
    thread: LaunchThread,
    work: impl FnOnce() -> Result<T, String> + Send,
) -> Result<T, String> {
    if thread == LaunchThread::Caller {
        return work();
    }
    let start = std::time::Instant::now();
    let out = like
        .client
        .exclusive(work)
        .map_err(|e| format!("cubecl's device thread: {e:?}"));
    waits::device_thread_call(start.elapsed());
    out?
}

/// Device pointers of burn's buffers for a kernel's parameters; each buffer stays alive while this is held
/// (hold it until the launch is queued: cubecl's stream then waits for the kernel before it can reuse them).
#[derive(Default)]
pub(crate) struct Pointers(Vec<Box<dyn std::any::Any>>);

impl Pointers {
    /// The device pointer of `t`'s first element, `t`'s buffer kept alive. (Kernels that index packed rows
    /// get their inputs through `contiguous_inputs` and their outputs from `empty_f32`; flash2 takes
    /// strided operands and passes their strides.)
    pub(crate) fn of(&mut self, t: &Primitive) -> Result<u64, String> {
        let (address, guard) = pointer(t)?;
        self.0.push(Box::new(guard));
        Ok(address)
    }
}

/// Launches the kernel `name` of `cache`'s kernels for `like`'s device on `blocks` blocks of `threads`
/// threads with `params`: on cubecl's stream (compiled from `instance`'s source, see
/// [`cubecl_stream::launch`]) unless `kernels.stream` is [`KernelStream::Side`], else on the side stream
/// ordered with cubecl's (built by `build` on first use; `family` names the kernels in errors).
///
/// # Safety
///
/// Every pointer in `params` must be a live buffer (see [`Pointers`]) of the extent the kernel reads or
/// writes through it.
pub(crate) unsafe fn launch_kernel<P: DeviceRepr>(
    (cache, kernels): (&'static LocalKey<KernelCache>, &Choices),
    like: &Primitive,
    (family, build): (SideFamily, &dyn Fn() -> Result<Compiled, String>),
    name: &str,
    instance: (&str, &dyn Fn() -> Result<String, String>),
    (blocks, threads): (usize, u32),
    params: &P,
) -> Result<(), String> {
    let grid = u32::try_from(blocks).map_err(|_| format!("{name}: {blocks} blocks"))?;
    if kernels.stream == KernelStream::Cubecl {
        // SAFETY: the caller's contract.
        return unsafe { cubecl_stream::launch(like, name, instance, (grid, 1, 1), threads, params) };
    }
    let config = LaunchConfig {
        grid_dim: (grid, 1, 1),
        block_dim: (threads, 1, 1),
        shared_mem_bytes: 0,
    };
    let sync = kernels.side_sync;
    with_cached(cache, like, family.name(), build, |compiled| {
        let f = compiled.function(name)?.clone();
        compiled.side.ordered((family, sync), |stream| {
            // SAFETY: the caller's contract (live buffers of the kernel's extents); cubecl's stream waits for
            // the kernel before anything queued later can free or reuse them.
            unsafe { stream.launch_builder(&f).arg(params).launch(config) }
                .map(|_| ())
                .map_err(|e| format!("{name}: {e:?}"))
        })
    })
}

/// Kernels compiled by NVRTC from one source and the side stream they run on, for one device and the
/// calling thread.
pub(crate) struct Compiled {
    /// The stream they run on.
    pub(crate) side: Side,
    functions: Vec<(String, CudaFunction)>,
}

impl Compiled {
    /// Compiles `source` with the options `options` gives for the device's major compute capability
    /// (`like`'s device, which must have `min_major` or newer) and loads the kernels `names`.
    pub(crate) fn compile(
        like: &Primitive,
        source: String,
        options: impl FnOnce(i32) -> CompileOptions,
        names: &[String],
        min_major: i32,
    ) -> Result<Self, String> {
        let side = Side::new(like)?;
        let (major, minor) = side
            .context()
            .compute_capability()
            .map_err(|e| format!("compute capability: {e:?}"))?;
        if major < min_major {
            return Err(format!(
                "compute capability {major}.{minor} (the kernels need {min_major}.0)"
            ));
        }
        let ptx = compile_ptx_with_opts(source, options(major)).map_err(|e| format!("NVRTC: {e:?}"))?;
        let module = side
            .context()
            .load_module(ptx)
            .map_err(|e| format!("loading the kernels: {e:?}"))?;
        let functions = names
            .iter()
            .map(|name| {
                let f = module
                    .load_function(name)
                    .map_err(|e| format!("kernel {name}: {e:?}"))?;
                Ok((name.clone(), f))
            })
            .collect::<Result<_, String>>()?;
        Ok(Self { side, functions })
    }

    /// The kernel `name`.
    pub(crate) fn function(&self, name: &str) -> Result<&CudaFunction, String> {
        self.functions
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, f)| f)
            .ok_or_else(|| format!("kernel {name} not compiled"))
    }

    /// Every kernel, by name.
    pub(crate) fn functions(&self) -> &[(String, CudaFunction)] {
        &self.functions
    }
}

/// A kernel source (umgen-cuda's `kernels/train/norm.cu`, …) as NVRTC compiles it: after the warp primitives of
/// `warp_device.cuh` and the bf16 stores of `bf16.cuh`, which it cannot include itself (NVRTC resolves no
/// include files).
pub(crate) fn kernel_source(source: &str) -> String {
    [umgen_cuda::source::PRIMITIVES, source].join("\n")
}

/// A thread's state of one kind (a source's [`Compiled`], a cuBLAS handle) by device and cubecl stream;
/// `Err` remembers why a device has none, so that the reason is found once. Every [`Side`] stream in it
/// meets the one cubecl stream it is kept for, as the protocol needs. (On cubecl's device thread,
/// [`on_device_thread`], every caller's stream has its own.)
pub(crate) type Cache<T> = RefCell<Vec<((usize, cubecl::stream_id::StreamId), Result<T, String>)>>;

/// A thread's [`Compiled`] of one source ([`Cache`]).
pub(crate) type KernelCache = Cache<Compiled>;

/// Runs `work` with `cache`'s state for `like`'s device and the calling cubecl stream, built by `build` on
/// first use (a failure is logged once, naming `what`, and returned every time).
pub(crate) fn with_cached<T, R>(
    cache: &'static LocalKey<Cache<T>>,
    like: &Primitive,
    what: &str,
    build: impl FnOnce() -> Result<T, String>,
    work: impl FnOnce(&mut T) -> Result<R, String>,
) -> Result<R, String> {
    let key = (like.device.index, cubecl::stream_id::StreamId::current());
    let device = key.0;
    cache.with_borrow_mut(|all| {
        if !all.iter().any(|(k, _)| *k == key) {
            let made = build();
            if let Err(why) = &made {
                tracing::warn!("{what} on cuda:{device}: {why}");
            }
            all.push((key, made));
        }
        match all.iter_mut().find(|(k, _)| *k == key) {
            Some((_, Ok(kernels))) => work(kernels),
            Some((_, Err(why))) => Err(why.clone()),
            None => Err(format!("no {what} for cuda:{device}")),
        }
    })
}
