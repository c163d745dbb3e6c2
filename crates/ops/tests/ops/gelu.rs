//! The CUDA C bias + GELU kernels (`src/gelu/gelu.cu`) run on the host: `gelu_emulator.cpp` runs every
//! thread of a block as a host thread and compares the forward pass (the activation) and the backward pass
//! (the pre-activation's gradient, the row groups' column sums of it) with a double-precision reference,
//! writing f32 and bf16: 16-byte pieces and single values, partial column chunks, more row groups than
//! rows, warps looping over the work.

#[test]
fn gelu_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("gelu/gelu_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches(" warps ").count(), 7, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
