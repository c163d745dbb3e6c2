//! The CUDA C attention kernels (`src/flash/flash2_tiles.cu`, `flash2.cu`) run on the host:
//! `flash2_emulator.cpp` compiles them with the system's C++ compiler, runs every thread of a block as a host
//! thread with the warp-level primitives (`mma.sync`, `ldmatrix`, shuffles, and Hopper's `wgmma` with its
//! swizzled shared-memory operands) emulated from their PTX definitions, and compares the output, log-sum-exp and the three gradients with a double-precision
//! reference (causal and not, ragged lengths, head sizes 32 and 64, f32 and bf16 operands, 4 and 8 warps per
//! block, a spare grid row, scores so low that an unmasked past-the-end key would give NaN, rows that do not
//! start on 16 bytes; the backward kernels' column step 32 and 64). The fragment layouts are what a GPU
//! run cannot debug cheaply; this checks them on every CI run.

#[test]
fn flash2_kernels_match_a_double_precision_reference_in_the_host_emulator() {
    // The backward kernels' column step as shipped (32) and doubled (the variant `SUB` selects), on
    // `mma.sync` and on `wgmma` (head size 64 on sm_90a: the A operands of the block's own rows read from
    // shared memory, the swizzled tile layout).
    let wgmma = "-DUMGEN_WGMMA_EMULATED";
    for defines in [&[][..], &["-DSUB=64"], &[wgmma], &[wgmma, "-DSUB=64"]] {
        let Some(report) = crate::emulator::run("flash/flash2_emulator.cpp", defines) else {
            return;
        };
        // Twenty cases (ten shapes, two of them with rows that do not start on 16 bytes, × 4 and 8 warps),
        // each with its five errors.
        assert_eq!(report.matches("warps, b").count(), 20, "{report}");
    }
}
