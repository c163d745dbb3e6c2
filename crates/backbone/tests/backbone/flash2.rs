//! The CUDA C attention kernels (`src/flash/flash2_tiles.cu`, `flash2.cu`) run on the host:
//! `flash2_emulator.cpp` compiles them with the system's C++ compiler, runs every thread of a block as a host
//! thread with the warp-level primitives (`mma.sync`, `ldmatrix`, shuffles) emulated from their PTX
//! definitions, and compares the output, log-sum-exp and the three gradients with a double-precision
//! reference (causal and not, ragged lengths, head sizes 32 and 64, f32 and bf16 operands, 4 and 8 warps per
//! block, a spare grid row; the backward kernels' column step 64 and 32). The fragment layouts are what a GPU
//! run cannot debug cheaply; this checks them on every CI run.

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

#[test]
fn flash2_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/flash/flash2_emulator.cpp");
    let Some(cxx) = compiler() else {
        // Rust needs a C toolchain to link, so a machine without a C++ compiler is rare; say so loudly.
        eprintln!("no C++ compiler ($CXX, c++, g++, clang++): the flash2 emulator check did not run");
        return;
    };
    // The backward kernels' column step as shipped (64) and halved (the variant `SUB` selects).
    for defines in [&[][..], &["-DSUB=32"][..]] {
        let binary = std::env::temp_dir().join(format!(
            "umgen-flash2-emulator-{}-{}",
            std::process::id(),
            defines.len()
        ));
        let built = Command::new(&cxx)
            .args(["-std=c++20", "-O2", "-pthread", "-Wno-unknown-pragmas"])
            .args(defines)
            .arg(&source)
            .arg("-o")
            .arg(&binary)
            .output()
            .expect("running the C++ compiler");
        assert!(
            built.status.success(),
            "{cxx} {defines:?} failed on {}:\n{}",
            source.display(),
            String::from_utf8_lossy(&built.stderr)
        );
        let run = Command::new(&binary).output().expect("running the emulator");
        let _ = std::fs::remove_file(&binary);
        let report = String::from_utf8_lossy(&run.stdout);
        assert!(
            run.status.success(),
            "the emulated kernels ({defines:?}) disagree:\n{report}"
        );
        // Twelve cases (six shapes × 4 and 8 warps), each with its five errors.
        assert_eq!(report.matches("warps, b").count(), 12, "{report}");
    }
}
