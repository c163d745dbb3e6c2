//! Progress bars: one style for every long command (they hide themselves when stderr is not a terminal).

/// A bar of `len` items labelled `what`.
pub fn bar(len: u64, what: &str) -> anyhow::Result<indicatif::ProgressBar> {
    let bar = indicatif::ProgressBar::new(len).with_message(what.to_string());
    bar.set_style(indicatif::ProgressStyle::with_template(
        "{bar:30} {pos}/{len} {msg} [{elapsed_precise} < {eta_precise}]",
    )?);
    Ok(bar)
}
