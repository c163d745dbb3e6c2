//! The CUDA C embedding-gradient kernels (`src/lookup/lookup.cu`) run on the host: `lookup_emulator.cpp`
//! runs the six kernels in order with every thread of a block as a host thread and compares the table's
//! gradient with a double-precision sum per id, and with itself on blocks of another size (the rows' order
//! fixes the sums, so the two must agree to the bit): uniform ids, one id in most rows (its rows span most
//! tiles), more ids than rows with some outside the table, one tile, one row wider than a block.

#[test]
fn lookup_kernels_match_a_double_precision_sum_in_the_host_emulator() {
    let Some(report) = crate::emulator::run("lookup/lookup_emulator.cpp", &[]) else {
        return;
    };
    assert_eq!(report.matches("): grad").count(), 5, "{report}");
    assert!(!report.contains("FAIL"), "{report}");
}
