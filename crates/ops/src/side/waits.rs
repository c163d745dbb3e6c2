//! Where the host waits around side-stream work, and a check that the work meets one cubecl stream only:
//! the two ways the ordering of [`super::Side`]'s protocol is examined (`umgen-kernel-bench repro`).

/// The kernel family whose launches the host waits for by default on the `train.kernel_stream = "side"`
/// path (docs/decisions/004-cuda-kernels-on-cubecl-stream.md): without the wait, one-step runs from one
/// seed gave a wrong gradient (a 3 % lower norm, every time the same value) in 1 of 15 runs of
/// `small-bundled` and 13 of 15 with burn's layer norm, on an H100; with it, none of 30 (15 each way).
/// Waiting before the launch instead cured it too; why either is needed was not found.
const WAITED_FOR: &str = "cross-entropy";

/// The kernel families that run on side streams, as `UMGEN_SIDE_SYNC` names them.
const FAMILIES: [&str; 5] = [
    "cross-entropy",
    "layer norm",
    "attention over time",
    "attention",
    "cuBLAS",
];

/// Host-side waits around the side-stream work of `family`: (before, after). `before` waits for cubecl's
/// stream to drain before the work is queued, `after` waits for the side stream to finish the work before
/// cubecl's stream queues more. By default only [`WAITED_FOR`] waits, after. `UMGEN_SIDE_SYNC=MODE[:FAMILY]`
/// (`MODE` one of `before`, `after`, `both`, `none`; `FAMILY` one of `cross-entropy`, `layer norm`,
/// `attention over time`, `attention`, `cuBLAS`) replaces that: every family, or only `FAMILY`, waits as
/// `MODE` says, for finding ordering faults (`umgen-kernel-bench repro`).
pub(super) fn host_sync(family: &str) -> (bool, bool) {
    type Mode = (bool, bool, Option<String>);
    static MODE: std::sync::OnceLock<Mode> = std::sync::OnceLock::new();
    let default = || (false, true, Some(WAITED_FOR.to_string()));
    let (before, after, only) = MODE.get_or_init(|| {
        let Ok(value) = std::env::var("UMGEN_SIDE_SYNC") else {
            return default();
        };
        let (mode, only) = match value.split_once(':') {
            Some((m, f)) => (m.to_string(), Some(f.to_string())),
            None => (value, None),
        };
        if let Some(f) = only.as_deref().filter(|f| !FAMILIES.contains(f)) {
            tracing::warn!(
                "UMGEN_SIDE_SYNC: no kernel family `{f}` (one of {}); the default applies",
                FAMILIES.join(", ")
            );
            return default();
        }
        match mode.as_str() {
            "before" => (true, false, only),
            "after" => (false, true, only),
            "both" => (true, true, only),
            "none" => (false, false, None),
            other => {
                tracing::warn!(
                    "UMGEN_SIDE_SYNC={other}: expected before, after, both or none; the default applies"
                );
                default()
            }
        }
    });
    match only {
        Some(f) if f != family => (false, false),
        _ => (*before, *after),
    }
}

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
