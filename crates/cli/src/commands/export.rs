//! `umgen export`: a bundle for `umgen generate` and outside runners (docs/export-format.md).

use crate::cli::ExportArgs;
use umgen::{GOLDEN_FILE, WeightDtype, export_bundle, write_golden};

/// Exports.
pub fn run(a: &ExportArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let dtype = match a.dtype.as_str() {
        "f32" => WeightDtype::F32,
        "bf16" => WeightDtype::Bf16,
        other => anyhow::bail!("--dtype {other}: expected f32 or bf16"),
    };
    let catalog = kinds.catalog()?;
    let m = export_bundle(&a.checkpoint, &a.out, dtype, &catalog)?;
    let bytes: u64 = m.files.values().map(|f| f.bytes).sum();
    tracing::info!(
        "{}: step {} of {} ({:?} weights, {} files, {:.1} MB)",
        a.out.display(),
        m.step,
        a.checkpoint.display(),
        m.dtype,
        m.files.len() + 1,
        bytes as f64 / 1e6
    );
    if a.golden > 0 {
        let size = write_golden(&a.out, a.golden, a.golden_seed, &catalog)?;
        tracing::info!(
            "{}: {} window(s) and their logits ({:.1} MB)",
            a.out.join(GOLDEN_FILE).display(),
            a.golden,
            size as f64 / 1e6
        );
    }
    Ok(())
}
