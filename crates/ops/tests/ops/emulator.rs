//! Builds and runs the host emulators of the CUDA C kernels (`src/**/*_emulator.cpp`) through
//! `umgen_cuda::emulator`.

use std::path::Path;
use umgen_cuda::emulator::{Emulated, run as build_and_run};

/// Compiles `src/{source}` with `defines`, runs it and asserts that it exits 0; its report, or `None`
/// (said on stderr) on a machine without a C++ compiler.
#[allow(clippy::print_stderr)] // a test's report that its check did not run
pub fn run(source: &str, defines: &[&str]) -> Option<String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("src").join(source);
    match build_and_run(&path, defines).expect("building the emulator") {
        Emulated::Agreed(report) => Some(report),
        Emulated::Disagreed(report) => {
            panic!("the emulated kernels of {source} ({defines:?}) disagree:\n{report}")
        }
        Emulated::NoCompiler => {
            // Rust needs a C toolchain to link, so a machine without a C++ compiler is rare; say so loudly.
            eprintln!("no C++ compiler ($CXX, c++, g++, clang++): the {source} check did not run");
            None
        }
    }
}
