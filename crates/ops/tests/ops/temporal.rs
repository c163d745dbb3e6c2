//! The CUDA C attention-over-time kernels (`src/temporal/temporal.cu`) run on the host:
//! `temporal_emulator.cpp` runs every thread of a block as a host thread with the warp shuffles emulated and
//! compares the output, log-sum-exp and the gradients of queries, keys and values with a double-precision
//! reference: head sizes 32, 64 and 128, 1 to 32 frames, causal and not, keys and values read from (and
//! their gradients written to) the two halves of one buffer, idle warps in the last block, sequences that
//! end inside a warp's block of rows.

#[test]
fn temporal_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("temporal/temporal_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 8, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
