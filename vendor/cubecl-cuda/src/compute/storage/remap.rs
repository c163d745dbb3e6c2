//! umgen: pages mapped onto physical memory that outlives them (`set_remapping`).
//!
//! cubecl's pools keep every page they take; a page left free by one tensor serves only later tensors
//! of its own size class, so a training step whose tensors come in many sizes holds 1.2–1.45× its live
//! set, and the driver's stream-ordered pool fragments as much when pages are handed back to it. Here a
//! page is a range of virtual addresses mapped (`cuMemMap`) chunk by chunk onto physical chunks of the
//! mapping granularity (2 MiB, `cuMemCreate`). When cubecl frees a page, its chunks go back to a free
//! list at once and any later page, of any size, maps them at its own addresses: the device memory held
//! is the pages in use, rounded up to 2 MiB, plus the free chunks.
//!
//! Ordering: pages are freed and mapped from one stream's pool; work already queued on that stream may
//! still read a freed page, and work queued after a new page maps the same memory runs after it on the
//! stream. The freed page's addresses stay mapped until a fence recorded at the release is reached, then
//! they are unmapped and given back.

use super::super::sync::Fence;
use cudarc::driver::sys::{
    self, CUdeviceptr, CUmemAccessDesc, CUmemAllocationProp, CUmemGenericAllocationHandle, CUresult,
};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Whether the pools of streams created from now on map their pages (see [`set_remapping`]).
static REMAPPING: AtomicBool = AtomicBool::new(false);
/// Physical memory held by every remapping storage of the process now, and at most, in bytes.
static HELD: AtomicU64 = AtomicU64::new(0);
static HELD_PEAK: AtomicU64 = AtomicU64::new(0);

/// umgen: from now on, the memory pools of new streams map their pages onto physical memory that is
/// reused across page sizes (`compute::storage::remap`); `false` (the default) takes each page with
/// `cuMemAllocAsync`. Call before any CUDA work.
pub fn set_remapping(on: bool) {
    REMAPPING.store(on, Ordering::Relaxed);
}

/// Whether new streams' pools map their pages.
pub(crate) fn remapping() -> bool {
    REMAPPING.load(Ordering::Relaxed)
}

/// umgen: the most physical memory the remapping pools held at once since the process started, in
/// bytes (0 without [`set_remapping`]): the device memory the pages took.
pub fn remapped_peak() -> u64 {
    HELD_PEAK.load(Ordering::Relaxed)
}

/// A mapped page: its addresses and the physical chunks behind them, in order.
#[derive(Debug)]
pub(crate) struct Page {
    pub ptr: CUdeviceptr,
    size: usize,
    chunks: Vec<usize>,
}

/// The physical memory of one stream's pool, in chunks of the mapping granularity (2 MiB): the driver
/// maps a physical allocation only whole (`cuMemMap`'s offset must be 0), so a page is mapped chunk by
/// chunk and any chunk serves any page.
pub(crate) struct Physical {
    chunk: usize,
    prop: CUmemAllocationProp,
    access: CUmemAccessDesc,
    handles: Vec<CUmemGenericAllocationHandle>,
    /// Indices into `handles` of the chunks no page maps.
    free: Vec<usize>,
    /// Addresses of freed pages, unmapped once their fence is reached.
    pending: Vec<(Fence, CUdeviceptr, usize)>,
    /// Whether [`Physical::map`] may create physical memory; when it may not and must, it refuses.
    pub allow_growth: bool,
    /// Whether a call to [`Physical::map`] was refused since this was last cleared.
    pub refused: bool,
}

/// A driver error as the storage reports it.
fn check(r: CUresult, what: &str) -> Result<(), String> {
    match r {
        CUresult::CUDA_SUCCESS => Ok(()),
        e => Err(format!("{what}: {e:?}")),
    }
}

impl Physical {
    /// Physical memory on the calling thread's current device.
    pub fn new() -> Result<Self, String> {
        let mut device = 0;
        // SAFETY: the server's context is current on the thread that creates its streams' storage.
        check(unsafe { sys::cuCtxGetDevice(&mut device) }, "cuCtxGetDevice")?;
        // SAFETY: both are plain C structs for which all-zero is a valid (empty) value.
        let (mut prop, mut access): (CUmemAllocationProp, CUmemAccessDesc) =
            unsafe { (std::mem::zeroed(), std::mem::zeroed()) };
        prop.type_ = sys::CUmemAllocationType::CU_MEM_ALLOCATION_TYPE_PINNED;
        prop.location.type_ = sys::CUmemLocationType::CU_MEM_LOCATION_TYPE_DEVICE;
        prop.location.id = device;
        access.location = prop.location;
        access.flags = sys::CUmemAccess_flags::CU_MEM_ACCESS_FLAGS_PROT_READWRITE;
        let mut granularity = 0;
        // SAFETY: `prop` describes device memory of `device`; the result is written to `granularity`.
        check(
            unsafe {
                sys::cuMemGetAllocationGranularity(
                    &mut granularity,
                    &prop,
                    sys::CUmemAllocationGranularity_flags::CU_MEM_ALLOC_GRANULARITY_RECOMMENDED,
                )
            },
            "cuMemGetAllocationGranularity",
        )?;
        Ok(Self {
            chunk: granularity.max(1),
            prop,
            access,
            handles: Vec::new(),
            free: Vec::new(),
            pending: Vec::new(),
            allow_growth: true,
            refused: false,
        })
    }

    /// A page of at least `size` bytes; `Ok(None)` when it needs more physical memory than the free
    /// chunks hold and growth is not allowed (then `refused` is set).
    pub fn map(&mut self, size: u64) -> Result<Option<Page>, String> {
        self.unmap_reached();
        let n = (size.max(1) as usize).div_ceil(self.chunk);
        if self.free.len() < n {
            if !self.allow_growth {
                self.refused = true;
                return Ok(None);
            }
            self.grow(n - self.free.len())?;
        }
        let chunks = self.free.split_off(self.free.len() - n);
        let size = n * self.chunk;
        let mut ptr = 0;
        // SAFETY: reserves `size` bytes of addresses, written to `ptr`.
        let mapped = check(
            unsafe { sys::cuMemAddressReserve(&mut ptr, size, self.chunk, 0, 0) },
            "cuMemAddressReserve",
        )
        .and_then(|()| {
            for (i, &c) in chunks.iter().enumerate() {
                // SAFETY: chunk `i` of the reserved range is not mapped yet; the chunk's physical
                // allocation is alive and no other page maps it.
                check(
                    unsafe {
                        sys::cuMemMap(ptr + (i * self.chunk) as u64, self.chunk, 0, self.handles[c], 0)
                    },
                    "cuMemMap",
                )?;
            }
            // SAFETY: the whole range was just mapped; `access` names this device.
            check(
                unsafe { sys::cuMemSetAccess(ptr, size, &self.access, 1) },
                "cuMemSetAccess",
            )
        });
        if let Err(e) = mapped {
            self.free.extend(chunks);
            return Err(e);
        }
        Ok(Some(Page { ptr, size, chunks }))
    }

    /// Frees `page`: its memory to the free list now, its addresses once the work queued on `stream`
    /// so far is done.
    pub fn release(&mut self, page: Page, stream: sys::CUstream) {
        self.free.extend(page.chunks);
        self.pending.push((Fence::new(stream), page.ptr, page.size));
        self.unmap_reached();
    }

    /// Unmaps and gives back the addresses of freed pages whose fence is reached.
    pub fn unmap_reached(&mut self) {
        let mut i = 0;
        while i < self.pending.len() {
            if self.pending[i].0.is_done() {
                let (fence, ptr, size) = self.pending.swap_remove(i);
                fence.destroy();
                // SAFETY: `[ptr, + size)` was mapped and reserved by `map`, and the work that used it is
                // done. An error leaves the addresses reserved, which costs address space only.
                unsafe {
                    let _ = sys::cuMemUnmap(ptr, size);
                    let _ = sys::cuMemAddressFree(ptr, size);
                }
            } else {
                i += 1;
            }
        }
    }

    /// Creates `n` more physical chunks, free.
    fn grow(&mut self, n: usize) -> Result<(), String> {
        for _ in 0..n {
            let mut handle = 0;
            // SAFETY: `prop` describes device memory; the handle is written to `handle`.
            check(
                unsafe { sys::cuMemCreate(&mut handle, self.chunk, &self.prop, 0) },
                "cuMemCreate",
            )?;
            self.free.push(self.handles.len());
            self.handles.push(handle);
            let held = HELD.fetch_add(self.chunk as u64, Ordering::Relaxed) + self.chunk as u64;
            HELD_PEAK.fetch_max(held, Ordering::Relaxed);
        }
        Ok(())
    }
}
