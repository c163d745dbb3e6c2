//! The CUDA C layer-norm kernels (`src/norm/norm.cu`) run on the host: `norm_emulator.cpp` runs every
//! thread of a block as a host thread with the warp shuffle emulated and compares the forward pass (output,
//! means, `1/σ`) and the backward pass (input gradient, the warps' column sums of the scale's and shift's
//! gradients) with a double-precision reference: rows narrower than a warp's capacity, widths that are not
//! multiples of 32, more warps than rows, every kernel size from 4 to 32 values a lane; and the bf16 output of
//! the bound forward pass (widths 384 and 768) against the f32 output rounded, to the bit.

#[test]
fn norm_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("norm/norm_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches(" warps:").count(), 6, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
