//! umgen: small host-to-device uploads (kernel metadata) through one pinned ring buffer per stream.
//!
//! Upstream stages every upload in a reservation of the pinned memory pool and hands it to the stream's
//! drop queue, which every 64 uploads waits for the fence of the previous 64. On a training step of a few
//! thousand launches that wait keeps the host at most about 128 uploads (a few ms of GPU work) ahead of
//! the device, and the GPU idles wherever the host's work per kernel is longer than the kernels (many
//! small operations); raising the drop queue's count instead made every reservation slower (the pool
//! searches its live slices). Here uploads are copied into a ring of pinned memory at a cursor, with a
//! fence recorded every [`MARK_EVERY`] uploads; a region is written again only after the fence that
//! followed its last use completed, so the host waits only when it is a whole ring (millions of uploads'
//! bytes) ahead. Completed fences are retired without waiting whenever a new one is recorded.

use crate::compute::sync::Fence;
use cudarc::driver::sys::CUstream;
use std::collections::VecDeque;

/// Bytes of pinned memory in a stream's ring.
const CAPACITY: usize = 8 << 20;

/// Uploads larger than this take the upstream path (the pinned pool and the drop queue).
pub(crate) const MAX_UPLOAD: usize = 64 << 10;

/// Uploads between two fences.
const MARK_EVERY: u32 = 64;

/// Offsets are kept 16-byte aligned, the alignment of any metadata a kernel reads.
const ALIGN: usize = 16;

/// The ring of one stream.
#[derive(Debug)]
pub(crate) struct UploadRing {
    /// Pinned host memory (`CAPACITY` bytes), allocated on first use.
    base: *mut u8,
    /// Bytes ever reserved, including the ends skipped at each wrap; the write offset is `head % CAPACITY`.
    head: u64,
    /// Bytes the device is known to be done with (every reservation below this has been copied).
    tail: u64,
    /// Fences recorded after the reservations up to `.0`, oldest first.
    marks: VecDeque<(u64, Fence)>,
    /// Uploads since the last fence.
    since_mark: u32,
}

// SAFETY: the ring is owned by its stream, which the server moves between threads as a whole; the pinned
// memory it points to is never shared outside it.
unsafe impl Send for UploadRing {}

impl Default for UploadRing {
    fn default() -> Self {
        Self {
            base: std::ptr::null_mut(),
            head: 0,
            tail: 0,
            marks: VecDeque::new(),
            since_mark: 0,
        }
    }
}

impl UploadRing {
    /// Copies `data` (at most [`MAX_UPLOAD`] bytes) into the ring and returns the pinned copy, which stays
    /// untouched until the device has passed the copy queued next on `stream`. `None` where pinned memory
    /// could not be allocated (the caller takes the upstream path).
    pub(crate) fn stage(&mut self, data: &[u8], stream: CUstream) -> Option<*const u8> {
        debug_assert!(data.len() <= MAX_UPLOAD);
        if self.base.is_null() {
            // SAFETY: a plain pinned allocation of the driver; freed never (it lives as long as the stream,
            // which upstream never destroys either).
            self.base = unsafe { cudarc::driver::result::malloc_host(CAPACITY, 0) }.ok()? as *mut u8;
        }
        let need = data.len().div_ceil(ALIGN).max(1) * ALIGN;
        let mut at = (self.head % CAPACITY as u64) as usize;
        if at + need > CAPACITY {
            // Skip the end of the ring: a reservation never wraps.
            self.head += (CAPACITY - at) as u64;
            at = 0;
        }
        self.reclaim(self.head + need as u64, stream);
        // SAFETY: `at + need <= CAPACITY`, and no queued copy reads this region any more (`reclaim`).
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), self.base.add(at), data.len()) };
        self.head += need as u64;
        Some(unsafe { self.base.add(at) } as *const u8)
    }

    /// Called after the copy of the last [`Self::stage`] was queued on `stream`: records a fence every
    /// [`MARK_EVERY`] uploads, retiring the completed ones first.
    pub(crate) fn queued(&mut self, stream: CUstream) {
        self.since_mark += 1;
        if self.since_mark < MARK_EVERY {
            return;
        }
        self.since_mark = 0;
        while let Some((end, fence)) = self.marks.front() {
            if !fence.is_done() {
                break;
            }
            self.tail = *end;
            if let Some((_, fence)) = self.marks.pop_front() {
                fence.destroy();
            }
        }
        self.marks.push_back((self.head, Fence::new(stream)));
    }

    /// Waits until every byte below `end - CAPACITY` is free: the oldest fences first, and, where the ring
    /// is full past the last fence, a new one.
    fn reclaim(&mut self, end: u64, stream: CUstream) {
        while end - self.tail > CAPACITY as u64 {
            let (mark, fence) = match self.marks.pop_front() {
                Some(m) => m,
                None => (self.head, Fence::new(stream)),
            };
            // An error here is the stream's (a failed kernel); upstream's drop queue ignores it too.
            let _ = fence.wait_sync();
            self.tail = mark;
        }
    }
}
