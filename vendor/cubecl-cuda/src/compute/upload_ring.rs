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

use crate::compute::ring::{Ring, RingFence};
use crate::compute::sync::Fence;
use cudarc::driver::sys::CUstream;

impl RingFence for Fence {
    fn is_done(&self) -> bool {
        Fence::is_done(self)
    }

    fn wait(self) {
        // An error here is the stream's (a failed kernel); upstream's drop queue ignores it too.
        let _ = self.wait_sync();
    }

    fn release(self) {
        self.destroy();
    }
}

/// Bytes of pinned memory in a stream's ring.
const CAPACITY: usize = 8 << 20;

/// Uploads larger than this take the upstream path (the pinned pool and the drop queue).
pub(crate) const MAX_UPLOAD: usize = 64 << 10;

/// The ring of one stream, its pinned memory allocated on first use.
#[derive(Debug)]
pub(crate) struct UploadRing(Ring<Fence>);

// SAFETY: the ring is owned by its stream, which the server moves between threads as a whole; the pinned
// memory it points to is never shared outside it.
unsafe impl Send for UploadRing {}

impl Default for UploadRing {
    fn default() -> Self {
        Self(Ring::new(std::ptr::null_mut(), CAPACITY))
    }
}

impl UploadRing {
    /// Copies `data` (at most [`MAX_UPLOAD`] bytes) into the ring and returns the pinned copy, which stays
    /// untouched until the device has passed the copy queued next on `stream`. `None` where pinned memory
    /// could not be allocated (the caller takes the upstream path).
    pub(crate) fn stage(&mut self, data: &[u8], stream: CUstream) -> Option<*const u8> {
        debug_assert!(data.len() <= MAX_UPLOAD);
        if !self.0.has_memory() {
            // SAFETY: a plain pinned allocation of the driver; freed never (it lives as long as the stream,
            // which upstream never destroys either).
            let base = unsafe { cudarc::driver::result::malloc_host(CAPACITY, 0) }.ok()?;
            self.0.set_memory(base as *mut u8);
        }
        Some(self.0.stage_with(data, || Fence::new(stream)))
    }

    /// Called after the copy of the last [`Self::stage`] was queued on `stream`: records a fence every 64
    /// uploads, retiring the passed ones first.
    pub(crate) fn queued(&mut self, stream: CUstream) {
        self.0.queued_with(|| Fence::new(stream));
    }
}
