//! Builds and runs the host emulators of the CUDA C kernels (`src/**/*_emulator.cpp`) with the system's C++
//! compiler.

use std::path::Path;
use std::process::Command;

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

/// Compiles `src/{source}` with `defines`, runs it and asserts that it exits 0; its report, or `None`
/// (said on stderr) on a machine without a C++ compiler.
#[allow(clippy::print_stderr)] // a test's report that its check did not run
pub fn run(source: &str, defines: &[&str]) -> Option<String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("src").join(source);
    let Some(cxx) = compiler() else {
        // Rust needs a C toolchain to link, so a machine without a C++ compiler is rare; say so loudly.
        eprintln!("no C++ compiler ($CXX, c++, g++, clang++): the {source} check did not run");
        return None;
    };
    let stem = source.replace(['/', '.'], "-");
    let binary = std::env::temp_dir().join(format!(
        "umgen-{stem}-{}-{}",
        std::process::id(),
        defines.join("-").replace('=', "")
    ));
    let built = Command::new(&cxx)
        .args(["-std=c++20", "-O2", "-pthread", "-Wno-unknown-pragmas"])
        .args(defines)
        .arg(&path)
        .arg("-o")
        .arg(&binary)
        .output()
        .expect("running the C++ compiler");
    assert!(
        built.status.success(),
        "{cxx} {defines:?} failed on {}:\n{}",
        path.display(),
        String::from_utf8_lossy(&built.stderr)
    );
    let run = Command::new(&binary).output().expect("running the emulator");
    let _ = std::fs::remove_file(&binary);
    let report = String::from_utf8_lossy(&run.stdout).into_owned();
    assert!(
        run.status.success(),
        "the emulated kernels of {source} ({defines:?}) disagree:\n{report}"
    );
    Some(report)
}
