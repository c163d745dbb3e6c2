//! The CUDA C sources, as NVRTC compiles them (it resolves no include files, so each source is the
//! concatenation of what it needs).

use crate::ops::ExecError;
use std::path::Path;

/// The warp- and block-level primitives and the bf16 loads and stores that every CUDA C kernel of umgen is
/// written against (`kernels/warp_device.cuh`, `kernels/bf16.cuh`); `kernels/warp_emulator.h` defines the
/// same names on the host.
pub const PRIMITIVES: &str = concat!(
    include_str!("kernels/warp_device.cuh"),
    "\n",
    include_str!("kernels/bf16.cuh"),
    "\n"
);

/// The training kernels umgen-ops launches (`kernels/train/`), each compiled after [`PRIMITIVES`].
pub mod train {
    /// AdamW and the gradients' global norm over slots of parameter tensors.
    pub const ADAMW: &str = include_str!("kernels/train/adamw.cu");
    /// Bias + GELU, forward and backward.
    pub const GELU: &str = include_str!("kernels/train/gelu.cu");
    /// The embedding table's gradient (a counting sort and sums over the sorted rows).
    pub const LOOKUP: &str = include_str!("kernels/train/lookup.cu");
    /// Layer norm, forward and backward, one warp a row.
    pub const NORM: &str = include_str!("kernels/train/norm.cu");
    /// Column sums over rows (a bias's gradient), with an optional bf16 copy.
    pub const ROWS: &str = include_str!("kernels/train/rows.cu");
    /// The TAR's attention over time on the rows as they lie.
    pub const TEMPORAL: &str = include_str!("kernels/train/temporal.cu");
    /// The cross-entropy's two passes over the logits, one warp a row.
    pub const XENT: &str = include_str!("kernels/train/xent.cu");
}

/// FlashAttention-2's forward and backward kernels (`kernels/flash2/`: warp primitives, tiles and fragment
/// products, the one-pass backward pass's queries' gradient, the passes), with their own
/// primitives: NVRTC compiles them alone.
pub const FLASH2: &str = concat!(
    include_str!("kernels/flash2/flash2_warp.cu"),
    include_str!("kernels/flash2/flash2_tiles.cu"),
    include_str!("kernels/flash2/flash2_dq.cu"),
    include_str!("kernels/flash2/flash2.cu")
);

/// [`FLASH2`] with only the bf16 forward kernel for head size `dh` (the generation engine's window pass
/// takes 32 or 64), `umgen_flash2_forward_bf16_{dh}`: the backward and f32 kernels would more than double
/// the first start's compilation, and each head size is its own program so that they compile side by side.
pub fn flash2_forward_bf16(dh: usize) -> String {
    format!(
        "#define UMGEN_INSTANCE KERNEL umgen_flash2_forward_bf16_{dh}(Params p) {{ forward<u16, {dh}>(p); }}\n{FLASH2}"
    )
}

/// The generation engine's kernel files, each with the kernels it defines: NVRTC compiles each with
/// [`engine_part`] as its own program, so that a start-up compiles them side by side.
pub const ENGINE_PARTS: [(&str, &[&str]); 4] = [
    ("gemv.cu", &["umgen_gemv"]),
    ("attend.cu", &["umgen_attend_rows", "umgen_attend_tiles"]),
    (
        "rows.cu",
        &[
            "umgen_rows_f",
            "umgen_rows_t",
            "umgen_bias_t",
            "umgen_embed",
            "umgen_shift_block",
            "umgen_align",
            "umgen_track",
        ],
    ),
    ("draw.cu", &["umgen_draw"]),
];

/// The source NVRTC compiles for the engine's kernel file `file` (one of [`ENGINE_PARTS`]) with weights and
/// operands in bf16 (`bf16`) or f32: the primitives, the element type, `engine_common.cuh` and the file.
/// `None` for a file that is not one of them.
pub fn engine_part(bf16: bool, file: &str) -> Option<String> {
    assemble(bf16, file, engine_part_file)
}

/// [`engine_part`] with each of `engine_common.cuh` and the kernel files read from `dir` where it has them
/// (`UMGEN_ENGINE_SOURCE=DIR`: a kernel change tried on a GPU without rebuilding umgen); the error names a
/// file that is there but cannot be read.
pub fn engine_part_from(bf16: bool, file: &str, dir: &Path) -> Result<Option<String>, ExecError> {
    let mut failed = None;
    let part = assemble(bf16, file, |name| {
        let path = dir.join(name);
        if !path.exists() {
            return engine_part_file(name);
        }
        std::fs::read_to_string(&path)
            .map_err(|e| failed = Some(ExecError::Invalid(format!("{}: {e}", path.display()))))
            .ok()
    });
    match failed {
        Some(e) => Err(e),
        None => Ok(part),
    }
}

/// The embedded text of one engine file.
fn engine_part_file(name: &str) -> Option<String> {
    let text = match name {
        "engine_common.cuh" => include_str!("kernels/engine_common.cuh"),
        "gemv.cu" => include_str!("kernels/gemv.cu"),
        "attend.cu" => include_str!("kernels/attend.cu"),
        "rows.cu" => include_str!("kernels/rows.cu"),
        "draw.cu" => include_str!("kernels/draw.cu"),
        _ => return None,
    };
    Some(text.to_owned())
}

/// The primitives, the element type, `engine_common.cuh` and `file`, each file's text from `text`.
fn assemble(bf16: bool, file: &str, mut text: impl FnMut(&str) -> Option<String>) -> Option<String> {
    if !ENGINE_PARTS.iter().any(|(part, _)| *part == file) {
        return None;
    }
    let wt = if bf16 {
        "#define WT u16\n"
    } else {
        "#define WT float\n"
    };
    Some(
        [
            PRIMITIVES.to_owned(),
            wt.to_owned(),
            text("engine_common.cuh")?,
            text(file)?,
        ]
        .join("\n"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_named_kernel_is_in_its_part_once_for_either_element_type() {
        for bf16 in [false, true] {
            for (file, kernels) in ENGINE_PARTS {
                // `KERNEL_RESIDENT(n) umgen_…` defines a kernel as `KERNEL umgen_…` does.
                let src = engine_part(bf16, file).expect(file);
                let src = (1..=8).fold(src, |s, n| {
                    s.replace(&format!("KERNEL_RESIDENT({n}) "), "KERNEL ")
                });
                assert_eq!(src.matches("KERNEL umgen_").count(), kernels.len(), "{file}");
                for k in kernels {
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
        assert!(engine_part(true, "flash2.cu").is_none());
    }

    #[test]
    fn a_source_directory_replaces_the_files_it_has_and_only_those() {
        let dir = std::env::temp_dir().join(format!("umgen-engine-source-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        std::fs::write(dir.join("attend.cu"), "// tried attention\n").expect("write");
        let src = engine_part_from(false, "attend.cu", &dir)
            .expect("read")
            .expect("attend.cu");
        assert!(src.contains("// tried attention"));
        assert!(!src.contains("KERNEL umgen_attend_rows("));
        assert!(src.contains("#define WT float"));
        let gemv = engine_part_from(false, "gemv.cu", &dir).expect("read");
        assert_eq!(gemv, engine_part(false, "gemv.cu"));
        // A file that is there but is not text is an error that names it.
        std::fs::write(dir.join("gemv.cu"), [0xff, 0xfe, 0x00]).expect("write");
        let err = engine_part_from(false, "gemv.cu", &dir).expect_err("not UTF-8");
        assert!(err.to_string().contains("gemv.cu"), "{err}");
        std::fs::remove_dir_all(&dir).expect("clean up");
    }
}
