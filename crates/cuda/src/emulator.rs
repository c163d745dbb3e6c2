//! Builds and runs a host emulator of CUDA C kernels (a `*_emulator.cpp` that includes
//! `kernels/warp_emulator.h` and the kernel sources) with the system's C++ compiler: how the kernels' tests
//! run them without a GPU.

use std::path::Path;
use std::process::Command;

/// What became of an emulator run.
#[derive(Debug)]
pub enum Emulated {
    /// It built, ran and exited 0: its report.
    Agreed(String),
    /// It built and ran, and exited non-zero: its report.
    Disagreed(String),
    /// There is no C++ compiler (`$CXX`, `c++`, `g++`, `clang++`) to build it with.
    NoCompiler,
}

/// The first C++ compiler found: `$CXX`, `c++`, `g++` or `clang++`.
fn compiler() -> Option<String> {
    std::env::var("CXX")
        .ok()
        .into_iter()
        .chain(["c++", "g++", "clang++"].map(String::from))
        .find(|c| {
            Command::new(c)
                .arg("--version")
                .output()
                .is_ok_and(|o| o.status.success())
        })
}

/// Compiles `source` with `defines` (C++20, -O2, threads) and runs it; an error if it does not build or
/// cannot run.
pub fn run(source: &Path, defines: &[&str]) -> Result<Emulated, String> {
    let Some(cxx) = compiler() else {
        return Ok(Emulated::NoCompiler);
    };
    let stem = source.to_string_lossy().replace(['/', '.'], "-");
    let binary = std::env::temp_dir().join(format!(
        "umgen-{stem}-{}-{}",
        std::process::id(),
        defines.join("-").replace(['=', '/'], "")
    ));
    let built = Command::new(&cxx)
        .args(["-std=c++20", "-O2", "-pthread", "-Wno-unknown-pragmas"])
        .args(defines)
        .arg(source)
        .arg("-o")
        .arg(&binary)
        .output()
        .map_err(|e| format!("running {cxx}: {e}"))?;
    if !built.status.success() {
        return Err(format!(
            "{cxx} {defines:?} failed on {}:\n{}",
            source.display(),
            String::from_utf8_lossy(&built.stderr)
        ));
    }
    let ran = Command::new(&binary)
        .output()
        .map_err(|e| format!("running {}: {e}", binary.display()));
    let _ = std::fs::remove_file(&binary);
    let ran = ran?;
    let report = String::from_utf8_lossy(&ran.stdout).into_owned();
    Ok(if ran.status.success() {
        Emulated::Agreed(report)
    } else {
        Emulated::Disagreed(report)
    })
}
