//! Progress bars: one style for every long command (they hide themselves when stderr is not a terminal).

/// A bar of `len` items labelled `what`.
pub fn bar(len: u64, what: &str) -> anyhow::Result<indicatif::ProgressBar> {
    let bar = indicatif::ProgressBar::new(len).with_message(what.to_string());
    bar.set_style(indicatif::ProgressStyle::with_template(
        "{bar:30} {pos}/{len} {msg} [{elapsed_precise} < {eta_precise}]",
    )?);
    Ok(bar)
}

/// A `--time-limit` in minutes (none: no limit), counted from when it is made.
pub struct TimeLimit {
    end: Option<std::time::Instant>,
}

impl TimeLimit {
    /// Starts counting `minutes`.
    pub fn minutes(minutes: Option<f64>) -> Self {
        Self {
            end: minutes.map(|m| std::time::Instant::now() + std::time::Duration::from_secs_f64(60.0 * m)),
        }
    }

    /// Whether the limit has passed at `step`; says so above `bar` when it has.
    pub fn reached(&self, bar: &indicatif::ProgressBar, step: u64) -> bool {
        let reached = self.end.is_some_and(|e| std::time::Instant::now() >= e);
        if reached {
            bar.suspend(|| tracing::info!("time limit reached at step {step}"));
        }
        reached
    }
}
