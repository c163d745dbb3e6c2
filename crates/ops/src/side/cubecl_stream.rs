//! umgen's CUDA C kernels launched as cubecl kernels, on cubecl's own stream
//! ([`crate::kernels::KernelStream::Cubecl`]).
//!
//! cubecl-cuda launches any [`CubeTask`] whose compiled form carries CUDA C source: it compiles the source
//! with NVRTC on first use (for the device's architecture), keeps the function by the task's
//! [`KernelId`], and launches it on the calling thread's stream with the launch's bindings, then its
//! packed scalars (`MetadataBindingInfo`) as the last parameter. umgen's kernels take one parameter, a
//! struct by value holding device pointers and sizes, so a launch binds no buffer and passes that struct's
//! bytes as the scalars: the kernel reads them as its `Params`, and being on cubecl's stream it runs after
//! everything cubecl queued before it and before everything queued after it.
//!
//! Each entry is compiled from a source that instantiates that entry's family of kernels only
//! (`UMGEN_INSTANCE`), not every kernel of the file, which NVRTC would otherwise compile once per entry.
//! The first launch of an entry on a thread waits for the device and reports a failure (a compile error,
//! an architecture the source does not support), so the caller can run burn's operations instead; after
//! that, launches never wait.
#![allow(unsafe_code)]

use super::fusion::Primitive;
use burn::cubecl::cuda::{CudaCompiler, CudaComputeKernel};
use cubecl::prelude::*;
use cubecl::server::{Binding, KernelArguments, MetadataBindingInfo};
use cubecl::{CompilationError, CubeTask};
use cubecl_cpp::shared::{Body, CubeIndexFlags, Elem, Flags, Item, SharedMemory};
use cudarc::driver::DeviceRepr;
use std::cell::RefCell;
use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::Arc;

/// One entry of a CUDA C source, as cubecl compiles and launches it.
#[derive(Clone)]
struct SourceKernel {
    /// The source, instantiating this entry (and its family) only.
    source: Arc<str>,
    /// A hash of `source`, part of the kernel's id (so that an edited source is not taken for the cached one).
    hash: u64,
    /// The entry point, `extern "C"`.
    entry: &'static str,
    cube_dim: CubeDim,
    /// Bytes of dynamic shared memory a block takes (`extern __shared__`), 0 for none.
    shared_bytes: usize,
}

impl KernelMetadata for SourceKernel {
    fn name(&self) -> &'static str {
        self.entry
    }

    fn id(&self) -> KernelId {
        KernelId::new::<Self>()
            .info((self.entry, self.hash, self.shared_bytes))
            .cube_dim(self.cube_dim)
    }

    fn address_type(&self) -> StorageType {
        AddressType::U32.unsigned_type()
    }
}

impl CubeTask<CudaCompiler> for SourceKernel {
    fn compile(
        &self,
        _compiler: &mut CudaCompiler,
        _options: &<CudaCompiler as cubecl::Compiler>::CompilationOptions,
        _mode: ExecutionMode,
        _address_type: StorageType,
    ) -> Result<CompiledKernel<CudaCompiler>, CompilationError> {
        Ok(CompiledKernel {
            entrypoint_name: self.entry.to_string(),
            debug_name: None,
            source: self.source.to_string(),
            repr: Some(representation(self.entry, self.cube_dim, self.shared_bytes)),
            cube_dim: self.cube_dim,
            debug_info: None,
        })
    }
}

/// cubecl-cuda takes the dynamic shared memory a launch needs from the kernel's representation, and
/// checks it against the device's (and raises the function's limit to it); umgen's kernels declare most of
/// theirs statically, so a body with no scalars, no buffers and one shared array of the dynamic bytes
/// (`shared_bytes`, none where 0) describes them.
fn representation(entry: &str, cube_dim: CubeDim, shared_bytes: usize) -> CudaComputeKernel {
    let address = Item::new(Elem::U32, 1, true);
    let shared_memories = (shared_bytes > 0)
        .then(|| SharedMemory::Array {
            index: 0,
            item: Item::new(Elem::U8, 1, true),
            length: shared_bytes,
            align: 16,
            offset: 0,
        })
        .into_iter()
        .collect();
    CudaComputeKernel {
        tensor_maps: Vec::new(),
        buffers: Vec::new(),
        scalars: Vec::new(),
        info: cubecl::Info::default(),
        meta_static_len: 0,
        body: Body {
            instructions: Vec::new(),
            shared_memories,
            pipelines: Vec::new(),
            barriers: Vec::new(),
            const_arrays: Vec::new(),
            local_arrays: Vec::new(),
            info_by_ptr: false,
            has_dynamic_meta: false,
            address_type: address,
        },
        cube_dim,
        cluster_dim: None,
        extensions: Vec::new(),
        flags: Flags {
            elem_fp4: false,
            elem_fp6: false,
            elem_fp8: false,
            elem_bf16: false,
            elem_f16: false,
            elem_tf32: false,
            indexes: CubeIndexFlags::default(),
            op_barrier: false,
            op_pipeline: false,
            inst_tma: false,
            inst_tma_im2col: false,
            inst_wmma: false,
            inst_ptx_wrappers: false,
            inst_async_copy: false,
            use_grid_constants: true,
            static_meta_length: 0,
            has_dynamic_meta: false,
            has_info: true,
            cube_dim,
            cluster_dim: None,
            address_type: address,
        },
        items: Default::default(),
        kernel_name: entry.to_string(),
    }
}

/// An entry's compiled-once state on this thread: its task, and whether a launch of it has been seen to
/// work (`Err` remembers why it did not, so later launches fall back at once).
type Entries = HashMap<(usize, String), Result<(SourceKernel, bool), String>>;

thread_local! {
    static ENTRIES: RefCell<Entries> = RefCell::new(HashMap::new());
}

/// The source NVRTC compiles for one entry: `source` with `UMGEN_INSTANCE` defined as `instance` (the
/// source's instance list then instantiates that one family; an empty `instance` keeps the whole source).
fn one_instance(source: &str, instance: &str) -> String {
    if instance.is_empty() {
        source.to_string()
    } else {
        format!("#define UMGEN_INSTANCE {instance}\n{source}")
    }
}

/// Launches `entry` on `grid` blocks of `threads` threads with `params`, on `like`'s cubecl stream; the
/// source is `source()` with `instance` (see [`one_instance`]), made on the entry's first use on this
/// thread. The first launch waits for the device and returns its failure, if any.
///
/// # Safety
///
/// Every pointer in `params` must be a live buffer of the extent the kernel reads or writes through it,
/// made on `like`'s stream (cubecl's stream order then keeps it alive for the kernel).
pub(crate) unsafe fn launch<P: DeviceRepr>(
    like: &Primitive,
    entry: &str,
    instance: (&str, &dyn Fn() -> Result<String, String>),
    grid: (u32, u32, u32),
    threads: u32,
    params: &P,
) -> Result<(), String> {
    // SAFETY: the caller's contract.
    unsafe { launch_bound(like, entry, instance, (grid, threads), Vec::new(), params) }
}

/// [`launch`] with `buffers` bound as the kernel's first parameters (one device pointer each, in order,
/// before `params`): cubecl resolves them on its device thread as it launches, so the host neither waits
/// for their addresses nor has to keep them alive, and cubecl orders the kernel after their writers on
/// other streams.
///
/// # Safety
///
/// As [`launch`]; the kernel must read and write each buffer within its extent.
pub(crate) unsafe fn launch_bound<P: DeviceRepr>(
    like: &Primitive,
    entry: &str,
    instance: (&str, &dyn Fn() -> Result<String, String>),
    (grid, threads): ((u32, u32, u32), u32),
    buffers: Vec<Binding>,
    params: &P,
) -> Result<(), String> {
    // SAFETY: the caller's contract.
    unsafe { launch_with(like, entry, instance, (grid, threads, 0), buffers, params) }
}

/// [`launch`] of a kernel that also takes `shared_bytes` of dynamic shared memory a block (its `extern
/// __shared__` array; cubecl raises the function's limit to it where it is over 48 KiB with the static).
///
/// # Safety
///
/// As [`launch`].
pub(crate) unsafe fn launch_shared<P: DeviceRepr>(
    like: &Primitive,
    entry: &str,
    instance: (&str, &dyn Fn() -> Result<String, String>),
    (grid, threads, shared_bytes): ((u32, u32, u32), u32, usize),
    params: &P,
) -> Result<(), String> {
    // SAFETY: the caller's contract.
    unsafe {
        launch_with(
            like,
            entry,
            instance,
            (grid, threads, shared_bytes),
            Vec::new(),
            params,
        )
    }
}

/// [`launch_bound`] with `shared_bytes` of dynamic shared memory a block.
///
/// # Safety
///
/// As [`launch_bound`].
unsafe fn launch_with<P: DeviceRepr>(
    like: &Primitive,
    entry: &str,
    (instance, source): (&str, &dyn Fn() -> Result<String, String>),
    (grid, threads, shared_bytes): ((u32, u32, u32), u32, usize),
    buffers: Vec<Binding>,
    params: &P,
) -> Result<(), String> {
    let key = (like.device.index, entry.to_string());
    let cube_dim = CubeDim::new_1d(threads);
    let (task, checked) = ENTRIES.with_borrow_mut(|all| {
        let known = all.entry(key.clone()).or_insert_with(|| {
            let text = one_instance(&source()?, instance);
            let mut hasher = DefaultHasher::new();
            text.hash(&mut hasher);
            // The name lives as long as cubecl's cache of the kernel: one leak per entry and thread.
            let entry: &'static str = Box::leak(entry.to_string().into_boxed_str());
            let task = SourceKernel {
                source: text.into(),
                hash: hasher.finish(),
                entry,
                cube_dim,
                shared_bytes,
            };
            Ok((task, false))
        });
        match known {
            Ok((task, checked)) => {
                let mut task = task.clone();
                task.cube_dim = cube_dim;
                Ok((task, *checked))
            }
            Err(why) => Err(why.clone()),
        }
    })?;
    let bytes = size_of::<P>();
    let mut data = vec![0u64; bytes.div_ceil(8)];
    // SAFETY: `P` is plain old data (`DeviceRepr`) of `bytes` bytes, copied into a buffer at least as long.
    unsafe {
        std::ptr::copy_nonoverlapping(
            (params as *const P).cast::<u8>(),
            data.as_mut_ptr().cast::<u8>(),
            bytes,
        )
    };
    let len = data.len();
    // The whole buffer is static metadata: cubecl passes it by value as the kernel's last parameter.
    let arguments = KernelArguments::new()
        .with_buffers(buffers)
        .with_info(MetadataBindingInfo::new(data, len));
    let client = &like.client;
    client.launch(
        Box::new(task.clone()),
        CubeCount::Static(grid.0, grid.1, grid.2),
        arguments,
    );
    if checked {
        return Ok(());
    }
    let result = burn::cubecl::future::block_on(client.sync()).map_err(|e| {
        // A compile error carries the whole source after its log.
        let text = e.to_string();
        let log = text.split("[Source]").next().unwrap_or_default().trim_end();
        format!("{entry} on cubecl's stream: {log}")
    });
    let state = result.clone().map(|()| (task, true));
    ENTRIES.with_borrow_mut(|all| all.insert(key, state));
    result
}
