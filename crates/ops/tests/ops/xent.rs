//! The CUDA C cross-entropy kernels (`src/xent/xent.cu`) run on the host: `xent_emulator.cpp` runs every
//! thread of a block as a host thread with the warp shuffle emulated and compares the forward pass (each
//! row's log-sum-exp) and the backward pass (the logits' gradient with the target weights taken off) with
//! a double-precision reference: the agent and map/image vocabularies, hard and smoothed targets, a
//! repeated id and one outside the row, logits far apart, rows narrower than a warp, more warps than rows.

#[test]
fn xent_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("xent/xent_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 4, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
