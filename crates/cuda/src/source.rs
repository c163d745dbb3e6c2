//! The CUDA C sources, as NVRTC compiles them (it resolves no include files, so each source is the
//! concatenation of what it needs).

/// The warp- and block-level primitives and the bf16 loads and stores that every CUDA C kernel of umgen is
/// written against (`kernels/warp_device.cuh`, `kernels/bf16.cuh`); `kernels/warp_emulator.h` defines the
/// same names on the host.
pub const PRIMITIVES: &str = concat!(
    include_str!("kernels/warp_device.cuh"),
    "\n",
    include_str!("kernels/bf16.cuh"),
    "\n"
);

/// FlashAttention-2's forward and backward kernels (`kernels/flash2/`: warp primitives, tiles and fragment
/// products, the three passes), with their own primitives: NVRTC compiles them alone.
pub const FLASH2: &str = concat!(
    include_str!("kernels/flash2/flash2_warp.cu"),
    include_str!("kernels/flash2/flash2_tiles.cu"),
    include_str!("kernels/flash2/flash2.cu")
);

/// [`FLASH2`] with only the bf16 forward kernels for head sizes 32 and 64 (the generation engine's window
/// pass): the backward and f32 kernels would more than double the first start's compilation.
pub fn flash2_forward_bf16() -> String {
    let instance =
        |d: usize| format!("KERNEL umgen_flash2_forward_bf16_{d}(Params p) {{ forward<u16, {d}>(p); }}");
    format!(
        "#define UMGEN_INSTANCE {} {}\n{FLASH2}",
        instance(32),
        instance(64)
    )
}

/// The generation engine's kernels (`gemv.cu`, `attend.cu`, `rows.cu`, `draw.cu`) with their weights and
/// operands in bf16 (`bf16`) or f32.
pub fn engine(bf16: bool) -> String {
    [
        PRIMITIVES,
        if bf16 {
            "#define WT u16\n"
        } else {
            "#define WT float\n"
        },
        include_str!("kernels/engine_common.cuh"),
        include_str!("kernels/gemv.cu"),
        include_str!("kernels/attend.cu"),
        include_str!("kernels/rows.cu"),
        include_str!("kernels/draw.cu"),
    ]
    .join("\n")
}

/// The kernels [`engine`] defines.
pub const ENGINE_KERNELS: [&str; 11] = [
    "umgen_gemv",
    "umgen_attend_rows",
    "umgen_attend_tiles",
    "umgen_rows_f",
    "umgen_rows_t",
    "umgen_bias_t",
    "umgen_embed",
    "umgen_shift_block",
    "umgen_align",
    "umgen_track",
    "umgen_draw",
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_named_kernel_is_in_the_source_once_for_either_element_type() {
        for bf16 in [false, true] {
            let src = engine(bf16);
            for k in ENGINE_KERNELS {
                let defined = format!("KERNEL {k}(");
                assert_eq!(src.matches(&defined).count(), 1, "{k}");
            }
            assert!(src.contains(if bf16 {
                "#define WT u16"
            } else {
                "#define WT float"
            }));
        }
    }
}
