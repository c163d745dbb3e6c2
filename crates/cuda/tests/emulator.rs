//! The generation engine's kernels (`src/kernels/{gemv,attend,rows,draw}.cu`) run on the host:
//! `engine_emulator.cpp` runs every thread of a block as a host thread with the warp shuffles emulated and
//! compares each kernel with a double-precision reference: every input and output mode of the
//! matrix-vector product (8-wide loads and the scalar tail), few-query attention over a cache as long as
//! the device position says, tiled attention over split instances (causal and not, ragged lengths), row
//! gathers with norms, periods and index lists, scatter-adds, embedding inputs, the action block's shift,
//! AMA's bilinear move, and the draw's token rules, greedy ties and the new-agent rule. Weights and
//! operands in f32 and in bf16.
#![allow(clippy::expect_used, clippy::panic, clippy::print_stderr, missing_docs)]

use std::path::Path;
use umgen_cuda::emulator::{Emulated, run};

#[test]
fn engine_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/kernels/engine_emulator.cpp");
    for defines in [["-DWT=float"], ["-DWT=u16"]] {
        match run(&source, &defines).expect("building the emulator") {
            Emulated::Agreed(report) => {
                // Eighteen cases and the summary line.
                assert_eq!(report.lines().count(), 19, "{report}");
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
