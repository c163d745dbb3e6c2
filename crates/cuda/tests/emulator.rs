//! The generation engine's kernels (`src/kernels/{gemv,attend,rows,draw}.cu`) run on the host:
//! `engine_emulator.cpp` runs every thread of a block as a host thread with the warp shuffles emulated and
//! compares each kernel with a double-precision reference: every input and output mode of the
//! matrix-vector product (8-wide loads and the scalar tail), few-query attention over a cache as long as
//! the device position says, tiled attention over split instances (causal and not, ragged lengths, 16-byte
//! and scalar loads), bias and GELU in place, row gathers with norms, periods and index lists (held in
//! registers and not), scatter-adds, embedding inputs, the action block's shift,
//! AMA's bilinear move, and the draw's token rules, greedy ties, sampled draws, a group's first token at
//! pad's untruncated share, the nucleus of the rest and the new-agent rule (against the boxes before
//! a new agent, and against every old agent of the frame). Weights and operands in f32 and in bf16.
#![allow(clippy::expect_used, clippy::panic, clippy::print_stderr, missing_docs)]

use std::path::Path;
use umgen_cuda::emulator::{Emulated, run};

#[test]
fn engine_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/kernels/engine_emulator.cpp");
    for defines in [["-DWT=float"], ["-DWT=u16"]] {
        match run(&source, &defines).expect("building the emulator") {
            Emulated::Agreed(report) => {
                // Forty-four cases and the summary line.
                assert_eq!(report.lines().count(), 45, "{report}");
                assert!(!report.contains("FAIL"), "{report}");
                assert!(report.contains("all cases agree"), "{report}");
            }
            Emulated::Disagreed(report) => panic!("{defines:?}:\n{report}"),
            Emulated::NoCompiler => {
                eprintln!("no C++ compiler: the engine kernels' emulator did not run");
                return;
            }
        }
    }
}

/// The tracked slots' kernel (`umgen_track` of `src/kernels/rows.cu`) run on the host by
/// `track_emulator.cpp`: random SUMO-like windows moved by constant acceleration, with and without the
/// follow rule, against a double-precision reference (slots whose results lie at a bin's edge or a rule's
/// threshold left out), and a hand-worked braking case.
#[test]
fn the_track_kernel_matches_a_double_precision_reference_in_the_host_emulator() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/kernels/track_emulator.cpp");
    match run(&source, &[]).expect("building the emulator") {
        Emulated::Agreed(report) => {
            assert!(report.contains("random windows               agrees"), "{report}");
            assert!(report.contains("follow, by hand              agrees"), "{report}");
            assert!(report.contains("all cases agree"), "{report}");
        }
        Emulated::Disagreed(report) => panic!("{report}"),
        Emulated::NoCompiler => eprintln!("no C++ compiler: the track kernel's emulator did not run"),
    }
}

/// The FlashAttention-2 kernels (`src/kernels/flash2/`) run on the host: `flash2_emulator.cpp` runs every
/// thread of a block as a host thread with the warp-level primitives (`mma.sync`, `ldmatrix`, shuffles, and
/// Hopper's `wgmma` with its swizzled shared-memory operands) emulated from their PTX definitions, and
/// compares the output, log-sum-exp and the three gradients with a double-precision reference (causal and
/// not, ragged lengths, head sizes 32 and 64, f32 and bf16 operands, 4 and 8 warps per block, a spare grid
/// row, scores so low that an unmasked past-the-end key would give NaN, rows that do not start on 16 bytes;
/// the backward kernels' column step 32 and 64), and on `wgmma` the one-pass backward pass's three
/// gradients (head size 64) into fresh results.
#[test]
fn flash2_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/kernels/flash2/flash2_emulator.cpp");
    // The backward kernels' column step as shipped (32) and doubled (the variant `SUB` selects), on
    // `mma.sync` and on `wgmma` (head size 64 on sm_90a: the A operands of the block's own rows read from
    // shared memory, the swizzled tile layout).
    let wgmma = "-DUMGEN_WGMMA_EMULATED";
    for defines in [&[][..], &["-DSUB=64"], &[wgmma], &[wgmma, "-DSUB=64"]] {
        match run(&source, defines).expect("building the emulator") {
            // Twenty cases (ten shapes, two of them with rows that do not start on 16 bytes, × 4 and 8
            // warps), each with its five errors.
            Emulated::Agreed(report) => {
                assert_eq!(report.matches("warps, b").count(), 20, "{report}");
                // The eight head-size-64 shapes × 4 and 8 warps, where the one-pass kernels exist.
                let one_pass = if defines.contains(&wgmma) { 16 } else { 0 };
                assert_eq!(report.matches("one-pass dq").count(), one_pass, "{report}");
            }
            Emulated::Disagreed(report) => panic!("{defines:?}:\n{report}"),
            Emulated::NoCompiler => {
                eprintln!("no C++ compiler: the flash2 kernels' emulator did not run");
                return;
            }
        }
    }
}
