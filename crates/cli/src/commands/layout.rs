//! `umgen layout`: the frame layout of a config.

use crate::cli::LayoutArgs;
use anyhow::Context;
use std::io::Write;
use umgen::UmgenConfig;
use umgen::modality::FrameLayout;

/// Loads the config, builds its registry and prints the layout.
pub fn run(args: &LayoutArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let path = &args.config.config;
    let (config, missing) = UmgenConfig::load(path, &args.config.set)?.without_missing_tokenizers();
    for m in missing {
        tracing::warn!(
            "modality `{m}`: its tokenizer does not exist yet; the fingerprint below does not include it"
        );
    }
    let registry = config.registry(&kinds.catalog()?)?;
    let layout = registry.layout()?;
    let params = umgen::backbone_spec(&registry, &config.backbone)?.param_count(&config.backbone);
    let mut out = std::io::stdout().lock();
    if args.json {
        let mut v = json(layout);
        v["backbone_parameters"] = params.into();
        writeln!(out, "{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        write_table(&mut out, &path.display().to_string(), layout)?;
        let b = &config.backbone;
        writeln!(
            out,
            "backbone: {params} parameters ({:.1} M; D {}, {} heads, CA_hist {}, CA_env {}, TAR {} × (temporal + spatial), OAR {})",
            params as f64 / 1e6,
            b.d_model,
            b.heads,
            b.ego_hist_layers,
            b.ego_env_layers,
            b.tar_layers,
            b.oar_layers
        )?;
    }
    out.flush().context("writing to stdout")
}

fn json(layout: &FrameLayout) -> serde_json::Value {
    serde_json::json!({
        "tokens_per_frame": layout.len(),
        "boundary_tokens": layout.boundary_tokens(),
        "fingerprint": layout.fingerprint(),
        "segments": layout.segments(),
    })
}

fn write_table(out: &mut impl Write, source: &str, layout: &FrameLayout) -> std::io::Result<()> {
    writeln!(out, "config       {source}")?;
    writeln!(out, "fingerprint  {}", layout.fingerprint())?;
    writeln!(out)?;
    // Names and kinds as wide as the longest (a plug-in's kind may be longer than the built-ins').
    let widest =
        |len: fn(&_) -> usize, least: usize| layout.segments().iter().map(len).max().unwrap_or(0).max(least);
    let name_w = widest(|s| s.modality.len(), 12);
    let kind_w = widest(|s| s.kind.len(), 8);
    writeln!(
        out,
        "{:<name_w$} {:<kind_w$} {:>6} {:>7} {:>7} {:>6} {:>6} {:>6} {:>8} {:>7}  grid",
        "modality", "kind", "start", "offset", "tokens", "end", "vocab", "embed", "start_id", "end_id"
    )?;
    let dash = |p: Option<usize>| p.map_or_else(|| "-".to_string(), |p| p.to_string());
    for s in layout.segments() {
        let grid = s
            .grid
            .map_or_else(|| "-".to_string(), |g| format!("{}x{}", g.rows, g.cols));
        writeln!(
            out,
            "{:<name_w$} {:<kind_w$} {:>6} {:>7} {:>7} {:>6} {:>6} {:>6} {:>8} {:>7}  {grid}",
            s.modality,
            s.kind,
            dash(s.start_pos),
            s.offset,
            s.tokens,
            dash(s.end_pos),
            s.vocab_size,
            s.embed_vocab,
            s.start_id,
            s.end_id,
        )?;
    }
    writeln!(out)?;
    let boundary = if layout.boundary_tokens() {
        "with"
    } else {
        "without"
    };
    writeln!(
        out,
        "N = {} tokens per frame ({} modalities, {boundary} start/end tokens)",
        layout.len(),
        layout.segments().len()
    )
}
