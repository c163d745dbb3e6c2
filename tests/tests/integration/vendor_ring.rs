//! The pinned upload ring of the vendored cubecl-cuda (`vendor/README.md`): its bookkeeping has no CUDA in
//! it, so its own tests (a stalled device, a device that keeps up, alignment) run here, in the CPU suite.
#![allow(unsafe_code, dead_code)]

#[path = "../../../vendor/cubecl-cuda/src/compute/ring.rs"]
mod ring;
