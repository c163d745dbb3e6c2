//! umgen's CUDA kernels: every CUDA C source (the training operations' in `src/kernels/train/`, which
//! umgen-ops launches on burn's streams, [`source::train`]; the generation engine's), their host emulators,
//! and the generation engine's operations and executor.
//!
//! The generation engine (`umgen_generate::engine`) runs the backbone's generation forward pass as a fixed
//! program of operations over buffers allocated once: [`ops`] names those operations (a matrix-vector
//! product with its prologue and epilogue, the attention variants, row gathers and norms, AMA, the tracked
//! slots' move, the draw with its token rules, cuBLAS products) and the [`ops::Exec`] interface that runs
//! them. It is always built, so that a host executor can run the same programs on the CPU (the tests, and
//! the reference a GPU run is checked against).
//!
//! With the `cuda` feature, `gpu::CudaExec` runs them on a GPU: the kernels in `src/kernels/*.cu` are CUDA
//! C compiled once by NVRTC at start-up for the element type of the weights (bf16 or f32), as machine code
//! kept in [`kernel_cache_dir`]; products of many rows go to cuBLAS, and a sequence of operations that
//! repeats (the decoding step) is captured once as a CUDA graph and replayed, so that a step costs one
//! launch from the host. Every `unsafe` of the GPU path
//! is in `gpu`; each launch first checks that every buffer it names holds the elements the kernel reads
//! or writes through it.
//!
//! The kernels also run on the host under `kernels/warp_emulator.h` (every CUDA thread a std::thread, warp
//! shuffles emulated): `kernels/engine_emulator.cpp` and `kernels/train/*_emulator.cpp` compare each with a
//! double-precision reference; the training kernels share the same primitives ([`source::PRIMITIVES`]).

pub mod emulator;
pub mod ops;
pub mod source;

#[cfg(feature = "cuda")]
pub mod gpu;

pub use ops::{Buf, Elem, Exec, ExecError, Op};

/// Where compiled CUDA kernels are kept between processes (the engine's machine code, and cubecl's
/// kernels where the command line points cubecl there): `$UMGEN_KERNEL_CACHE` (`off` for nowhere), else
/// `$XDG_CACHE_HOME/umgen/kernels`, else `~/.cache/umgen/kernels`.
pub fn kernel_cache_dir() -> Option<std::path::PathBuf> {
    match std::env::var_os("UMGEN_KERNEL_CACHE") {
        Some(v) if v == "off" => None,
        Some(v) if !v.is_empty() => Some(v.into()),
        _ => std::env::var_os("XDG_CACHE_HOME")
            .filter(|v| !v.is_empty())
            .map(std::path::PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| std::path::Path::new(&h).join(".cache")))
            .map(|c| c.join("umgen").join("kernels")),
    }
}
