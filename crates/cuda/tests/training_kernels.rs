//! The training kernels (`src/kernels/train/*.cu`, launched by umgen-ops) run on the host: each
//! `*_emulator.cpp` runs every thread of a block as a host thread with the warp primitives emulated and
//! compares the kernels with a double-precision reference.
#![allow(clippy::expect_used, clippy::panic, clippy::print_stderr, missing_docs)]

use std::path::Path;
use umgen_cuda::emulator::{Emulated, run};

/// Compiles `src/kernels/train/{source}`, runs it and asserts that it exits 0; its report, or `None` (said
/// on stderr) on a machine without a C++ compiler.
fn emulated(source: &str) -> Option<String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("src/kernels/train")
        .join(source);
    match run(&path, &[]).expect("building the emulator") {
        Emulated::Agreed(report) => Some(report),
        Emulated::Disagreed(report) => panic!("the emulated kernels of {source} disagree:\n{report}"),
        Emulated::NoCompiler => {
            // Rust needs a C toolchain to link, so a machine without a C++ compiler is rare; say so loudly.
            eprintln!("no C++ compiler ($CXX, c++, g++, clang++): the {source} check did not run");
            None
        }
    }
}

/// The CUDA C bias + GELU kernels (`src/kernels/train/gelu.cu`) run on the host: `gelu_emulator.cpp` runs every
/// thread of a block as a host thread and compares the forward pass (the activation) and the backward pass
/// (the pre-activation's gradient, the row groups' column sums of it) with a double-precision reference,
/// writing f32 and bf16: 16-byte pieces and single values, partial column chunks, more row groups than
/// rows, warps looping over the work.
#[test]
fn gelu_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = emulated("gelu_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches(" warps ").count(), 7, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}

/// The CUDA C embedding-gradient kernels (`src/kernels/train/lookup.cu`) run on the host: `lookup_emulator.cpp`
/// runs the six kernels in order with every thread of a block as a host thread and compares the table's
/// gradient with a double-precision sum per id, and with itself on blocks of another size (the rows' order
/// fixes the sums, so the two must agree to the bit): uniform ids, one id in most rows (its rows span most
/// tiles), more ids than rows with some outside the table, one tile, one row wider than a block.
#[test]
fn lookup_kernels_match_a_double_precision_sum_in_the_host_emulator() {
    let Some(report) = emulated("lookup_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches("): grad").count(), 5, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}

/// The CUDA C layer-norm kernels (`src/kernels/train/norm.cu`) run on the host: `norm_emulator.cpp` runs every
/// thread of a block as a host thread with the warp shuffle emulated and compares the forward pass (output,
/// means, `1/σ`) and the backward pass (input gradient, the warps' column sums of the scale's and shift's
/// gradients) with a double-precision reference: rows narrower than a warp's capacity, widths that are not
/// multiples of 32, more warps than rows, every kernel size from 4 to 32 values a lane; and the bf16 output of
/// the bound forward pass (widths 384 and 768) against the f32 output rounded, to the bit.
#[test]
fn norm_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = emulated("norm_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 6, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}

/// The CUDA C column-sum kernel (`src/kernels/train/rows.cu`) runs on the host: `rows_emulator.cpp` runs its two
/// launches with every thread of a block as a host thread and compares the sums with a double-precision
/// reference, and with themselves on blocks of another size (the phases fix the order, so the two must agree
/// to the bit): partial column tiles and groups, one launch for few rows, a matrix narrower than a warp,
/// bf16 rows (summed in f32), and f32 rows whose bf16 copy the first launch writes.
#[test]
fn row_sum_kernel_matches_a_double_precision_sum_in_the_host_emulator() {
    let Some(report) = emulated("rows_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches(": sums").count(), 8, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}

/// The CUDA C attention-over-time kernels (`src/kernels/train/temporal.cu`) run on the host:
/// `temporal_emulator.cpp` runs every thread of a block as a host thread with the warp shuffles emulated and
/// compares the output, log-sum-exp and the gradients of queries, keys and values with a double-precision
/// reference: head sizes 32, 64 and 128, 1 to 32 frames, causal and not, keys and values read from (and
/// their gradients written to) the two halves of one buffer, idle warps in the last block, sequences that
/// end inside a warp's block of rows.
#[test]
fn temporal_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = emulated("temporal_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 8, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}

/// The CUDA C cross-entropy kernels (`src/kernels/train/xent.cu`) run on the host: `xent_emulator.cpp` runs every
/// thread of a block as a host thread with the warp shuffle emulated and compares the forward pass (each
/// row's log-sum-exp) and the backward pass (the logits' gradient with the target weights taken off) with
/// a double-precision reference: the agent and map/image vocabularies, hard and smoothed targets, a
/// repeated id and one outside the row, logits far apart, rows narrower than a warp, more warps than rows.
#[test]
fn xent_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = emulated("xent_emulator.cpp") else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 4, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
