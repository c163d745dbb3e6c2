//! Checks of [`super::Side`]'s protocol: that side-stream work meets one cubecl stream only, and how often
//! the host called cubecl's device thread (`umgen-kernel-bench repro`; where the host waits around
//! side-stream work is `crate::Kernels::side_sync`).

/// Times side-stream work took a buffer made on another cubecl stream than the one it is ordered with (a
/// side stream meets only the stream it is kept for, `super::Cache`): the protocol orders the work with
/// one cubecl stream only (the first is logged).
static FOREIGN: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Counts and logs (the first) use of side-stream work across cubecl streams.
pub(super) fn foreign(what: std::fmt::Arguments) {
    if FOREIGN.fetch_add(1, std::sync::atomic::Ordering::Relaxed) == 0 {
        tracing::warn!("side stream: {what}");
    }
}

/// How many times side-stream work met another cubecl stream than the one it is ordered with.
pub fn foreign_streams() -> usize {
    FOREIGN.load(std::sync::atomic::Ordering::Relaxed)
}

/// Calls made on cubecl's device thread ([`super::on_device_thread`]) and the host's time in them, in ns.
static DEVICE_CALLS: [std::sync::atomic::AtomicU64; 2] = [
    std::sync::atomic::AtomicU64::new(0),
    std::sync::atomic::AtomicU64::new(0),
];

/// Counts one call on cubecl's device thread that held the calling thread for `took`.
pub(super) fn device_thread_call(took: std::time::Duration) {
    use std::sync::atomic::Ordering::Relaxed;
    DEVICE_CALLS[0].fetch_add(1, Relaxed);
    DEVICE_CALLS[1].fetch_add(u64::try_from(took.as_nanos()).unwrap_or(u64::MAX), Relaxed);
}

/// How many custom operations this process ran on cubecl's device thread, and the calling threads' time
/// in those calls (seconds): each call waits until that thread has run everything queued before it, so
/// the time says how much the host's two threads were serialised (`bench train` prints it per step).
pub fn device_thread_calls() -> (u64, f64) {
    use std::sync::atomic::Ordering::Relaxed;
    (
        DEVICE_CALLS[0].load(Relaxed),
        DEVICE_CALLS[1].load(Relaxed) as f64 * 1e-9,
    )
}
