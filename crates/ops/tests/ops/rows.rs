//! The CUDA C column-sum kernel (`src/rows/rows.cu`) runs on the host: `rows_emulator.cpp` runs its two
//! launches with every thread of a block as a host thread and compares the sums with a double-precision
//! reference, and with themselves on blocks of another size (the phases fix the order, so the two must agree
//! to the bit): partial column tiles and groups, one launch for few rows, a matrix narrower than a warp,
//! bf16 rows (summed in f32), and f32 rows whose bf16 copy the first launch writes.

#[test]
fn row_sum_kernel_matches_a_double_precision_sum_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("rows/rows_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches(": sums").count(), 8, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
