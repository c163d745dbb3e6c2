//! umgen: the bookkeeping of `upload_ring.rs`'s ring, without CUDA: where each upload goes, which fence
//! frees which bytes, when to wait. Kept apart so that umgen's CPU test suite can run its tests
//! (`tests/tests/vendor_ring.rs` includes this file).

use std::collections::VecDeque;

/// What the ring needs of a fence (a CUDA event here; a mock in the tests).
pub trait RingFence {
    /// Whether the device has passed it (without waiting).
    fn is_done(&self) -> bool;
    /// Waits until the device has passed it, then releases it.
    fn wait(self);
    /// Releases a fence the device has passed.
    fn release(self);
}

/// Uploads between two fences.
const MARK_EVERY: u32 = 64;

/// Offsets are kept 16-byte aligned, the alignment of any metadata a kernel reads.
pub const ALIGN: usize = 16;

/// A ring over `capacity` bytes at `base`, its fences of type `F`.
#[derive(Debug)]
pub struct Ring<F: RingFence> {
    /// Pinned host memory (`capacity` bytes), owned by the caller.
    base: *mut u8,
    /// Its size.
    capacity: usize,
    /// Bytes ever reserved, including the ends skipped at each wrap; the write offset is `head % CAPACITY`.
    head: u64,
    /// Bytes the device is known to be done with (every reservation below this has been copied).
    tail: u64,
    /// Fences recorded after the reservations up to `.0`, oldest first.
    marks: VecDeque<(u64, F)>,
    /// Uploads since the last fence.
    since_mark: u32,
}

impl<F: RingFence> Ring<F> {
    /// A ring over `capacity` bytes at `base` (null until the caller allocates it: [`Ring::set_memory`]).
    pub fn new(base: *mut u8, capacity: usize) -> Self {
        Self {
            base,
            capacity,
            head: 0,
            tail: 0,
            marks: VecDeque::new(),
            since_mark: 0,
        }
    }

    /// Whether the ring has its memory.
    pub fn has_memory(&self) -> bool {
        !self.base.is_null()
    }

    /// Gives the ring its memory (`capacity` bytes at `base`, kept alive by the caller).
    pub fn set_memory(&mut self, base: *mut u8) {
        self.base = base;
    }

    /// Copies `data` into the ring at the cursor and returns where; bytes of earlier uploads are written again
    /// only after a fence (from `fence` when none is recorded) that followed them was passed. The ring must
    /// have its memory and `data` fit it.
    pub fn stage_with(&mut self, data: &[u8], fence: impl Fn() -> F) -> *const u8 {
        let need = data.len().div_ceil(ALIGN).max(1) * ALIGN;
        let mut at = (self.head % self.capacity as u64) as usize;
        if at + need > self.capacity {
            // Skip the end of the ring: a reservation never wraps.
            self.head += (self.capacity - at) as u64;
            at = 0;
        }
        self.reclaim(self.head + need as u64, fence);
        // SAFETY: `at + need <= capacity`, and no queued copy reads this region any more (`reclaim`).
        unsafe { std::ptr::copy_nonoverlapping(data.as_ptr(), self.base.add(at), data.len()) };
        self.head += need as u64;
        // SAFETY: within the allocation, as above.
        unsafe { self.base.add(at) as *const u8 }
    }

    /// Called once the copy of the last [`Ring::stage_with`] is queued: records a fence from `fence` every
    /// [`MARK_EVERY`] uploads, retiring the passed ones first.
    pub fn queued_with(&mut self, fence: impl Fn() -> F) {
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
            if let Some((_, done)) = self.marks.pop_front() {
                done.release();
            }
        }
        self.marks.push_back((self.head, fence()));
    }

    /// Waits until every byte below `end - CAPACITY` is free: the oldest fences first, and, where the ring
    /// is full past the last fence, a new one.
    fn reclaim(&mut self, end: u64, fence: impl Fn() -> F) {
        while end - self.tail > self.capacity as u64 {
            let (mark, oldest) = match self.marks.pop_front() {
                Some(m) => m,
                None => (self.head, fence()),
            };
            if oldest.is_done() {
                oldest.release();
            } else {
                oldest.wait();
            }
            self.tail = mark;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::RefCell;
    use std::rc::Rc;

    /// A fence over a shared count of copies the mock device has done: passed once it reaches `at`
    /// (the number of copies queued before it); waiting on it makes the device catch up, as a real wait
    /// returns only then.
    struct Mock {
        at: usize,
        done: Rc<RefCell<usize>>,
        waits: Rc<RefCell<usize>>,
    }

    impl RingFence for Mock {
        fn is_done(&self) -> bool {
            *self.done.borrow() >= self.at
        }
        fn wait(self) {
            *self.waits.borrow_mut() += 1;
            let mut d = self.done.borrow_mut();
            *d = (*d).max(self.at);
        }
        fn release(self) {}
    }

    /// A ring of `capacity` bytes over host memory, and the mock device's state.
    struct Rig {
        ring: Ring<Mock>,
        _memory: Vec<u8>,
        done: Rc<RefCell<usize>>,
        waits: Rc<RefCell<usize>>,
        /// Copies queued: where each one's source lies and what it must still hold.
        queued: Vec<(*const u8, Vec<u8>)>,
    }

    impl Rig {
        fn new(capacity: usize) -> Self {
            let mut memory = vec![0u8; capacity];
            let ring = Ring::new(memory.as_mut_ptr(), capacity);
            Self {
                ring,
                _memory: memory,
                done: Rc::new(RefCell::new(0)),
                waits: Rc::new(RefCell::new(0)),
                queued: Vec::new(),
            }
        }

        fn fence(&self) -> impl Fn() -> Mock + use<> {
            let (at, done, waits) = (self.queued.len(), self.done.clone(), self.waits.clone());
            move || Mock {
                at,
                done: done.clone(),
                waits: waits.clone(),
            }
        }

        /// Stages `data` and queues its copy; checks that every copy the device has not done yet still
        /// reads what was staged for it.
        fn upload(&mut self, data: &[u8]) {
            let fence = self.fence();
            let ptr = self.ring.stage_with(data, fence);
            self.queued.push((ptr, data.to_vec()));
            let fence = self.fence();
            self.ring.queued_with(fence);
            let done = *self.done.borrow();
            for (i, (ptr, want)) in self.queued.iter().enumerate().skip(done) {
                // SAFETY: `ptr` points into the rig's memory, `want.len()` bytes from it.
                let got = unsafe { std::slice::from_raw_parts(*ptr, want.len()) };
                assert_eq!(got, &want[..], "copy {i} (device at {done}) was overwritten");
            }
        }
    }

    fn bytes(i: usize, len: usize) -> Vec<u8> {
        (0..len).map(|j| (i * 31 + j * 7) as u8).collect()
    }

    #[test]
    fn a_stalled_device_makes_the_ring_wait_and_nothing_queued_is_overwritten() {
        // 4 KiB: a few hundred uploads fill it, so it wraps many times while the device does nothing.
        let mut rig = Rig::new(4096);
        for i in 0..2000 {
            rig.upload(&bytes(i, 8 + (i * 13) % 90));
        }
        assert!(*rig.waits.borrow() > 0, "a full ring must wait for the device");
        assert!(rig.ring.head > 8 * 4096, "the ring wrapped");
    }

    #[test]
    fn a_device_that_keeps_up_is_never_waited_for() {
        let mut rig = Rig::new(4096);
        for i in 0..2000 {
            rig.upload(&bytes(i, 16 + i % 48));
            // The device finishes every copy as soon as it is queued.
            *rig.done.borrow_mut() = rig.queued.len();
        }
        assert_eq!(*rig.waits.borrow(), 0);
        assert!(rig.ring.marks.len() <= 1, "passed fences are retired");
    }

    #[test]
    fn reservations_are_aligned_and_never_wrap() {
        let mut rig = Rig::new(1000);
        for i in 0..300 {
            rig.upload(&bytes(i, 1 + (i * 37) % 200));
            let (ptr, want) = rig.queued.last().expect("an upload");
            let off = *ptr as usize - rig.ring.base as usize;
            assert_eq!(off % ALIGN, 0, "upload {i} at {off}");
            assert!(off + want.len() <= 1000, "upload {i} at {off} runs past the end");
        }
    }
}
