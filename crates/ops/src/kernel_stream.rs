//! Where umgen's CUDA C kernels (attention, layer norm, attention over time, cross-entropy) and cuBLAS's
//! products run (`train.kernel_stream`): on cubecl's own stream, or on side streams of umgen's.
//!
//! On cubecl's stream each kernel is launched as a cubecl kernel whose source is umgen's CUDA C (cubecl
//! compiles it with NVRTC, caches it and launches it in order with its own kernels), and each cuBLAS
//! product is queued on the stream cubecl resolved for its operands (`last_stream` of the vendored
//! cubecl-cuda, `vendor/README.md`), so nothing has to order two streams: no flag kernels, no host round
//! trip per launch. On a side stream each launch is ordered with cubecl's through device flags
//! (`side.rs`). cuBLAS's products also take the side stream when the custom operations launch from the
//! caller's thread (`train.launch_thread = "caller"`), where no cubecl stream is resolved.
//!
//! Independently, the custom operations' launches (with the device pointers they fetch) run on cubecl's
//! device thread by default (`train.launch_thread = "device"`), each operation as one call the host waits
//! for, rather than on the calling thread with one round trip to the device thread per pointer
//! (`"caller"`).

use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};

/// Where the CUDA C kernels and cuBLAS's products run (`train.kernel_stream`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KernelStream {
    /// cubecl's own stream, launched as cubecl kernels. The default.
    #[default]
    Cubecl,
    /// A side stream per kernel family, ordered with cubecl's through device flags (as before; for
    /// comparing the two).
    Side,
}

/// Whether [`KernelStream::Side`] was chosen.
static SIDE: AtomicBool = AtomicBool::new(false);

/// Chooses where the CUDA C kernels of every pass this process runs from now on go.
pub fn select(stream: KernelStream) {
    SIDE.store(stream == KernelStream::Side, Ordering::Relaxed);
}

/// What [`select`] chose ([`KernelStream::Cubecl`] unless told otherwise).
pub fn selected() -> KernelStream {
    if SIDE.load(Ordering::Relaxed) {
        KernelStream::Side
    } else {
        KernelStream::Cubecl
    }
}

/// Which thread launches umgen's custom operations' work (`train.launch_thread`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LaunchThread {
    /// cubecl's device thread, one blocking call per operation. The default.
    #[default]
    Device,
    /// The calling thread, a blocking call per device pointer (as before; for comparing the two).
    Caller,
}

/// Whether [`LaunchThread::Caller`] was chosen.
static CALLER: AtomicBool = AtomicBool::new(false);

/// Chooses which thread launches the custom operations' work of every pass this process runs from now on.
pub fn select_thread(thread: LaunchThread) {
    CALLER.store(thread == LaunchThread::Caller, Ordering::Relaxed);
}

/// What [`select_thread`] chose ([`LaunchThread::Device`] unless told otherwise).
pub fn selected_thread() -> LaunchThread {
    if CALLER.load(Ordering::Relaxed) {
        LaunchThread::Caller
    } else {
        LaunchThread::Device
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_the_choice_is_kept() {
        let parsed: Vec<KernelStream> =
            serde_json::from_str(r#"["cubecl", "side"]"#).expect("both names parse");
        assert_eq!(parsed, [KernelStream::Cubecl, KernelStream::Side]);
        assert!(serde_json::from_str::<KernelStream>(r#""stream""#).is_err());
        select(KernelStream::Side);
        assert_eq!(selected(), KernelStream::Side);
        select(KernelStream::Cubecl);
        assert_eq!(selected(), KernelStream::Cubecl);
        let parsed: Vec<LaunchThread> =
            serde_json::from_str(r#"["device", "caller"]"#).expect("both names parse");
        assert_eq!(parsed, [LaunchThread::Device, LaunchThread::Caller]);
        select_thread(LaunchThread::Caller);
        assert_eq!(selected_thread(), LaunchThread::Caller);
        select_thread(LaunchThread::Device);
        assert_eq!(selected_thread(), LaunchThread::Device);
    }
}
