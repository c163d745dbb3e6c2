//! Logging setup: `tracing` to stderr, filtered by `UMGEN_LOG` or the `-v` count.

use std::io::IsTerminal;
use tracing_subscriber::EnvFilter;

/// Installs the global subscriber. Without `UMGEN_LOG`, umgen logs at info (debug with `-v`, trace with
/// `-vv`) and dependencies at warn; ranks other than 0 of a data-parallel job only warn, so progress is
/// printed once.
pub fn init(verbose: u8) {
    let rank = std::env::var("RANK")
        .or_else(|_| std::env::var("SLURM_PROCID"))
        .ok()
        .and_then(|r| r.parse::<usize>().ok())
        .unwrap_or(0);
    let level = match (rank, verbose) {
        (0, 0) => "info",
        (0, 1) => "debug",
        (0, _) => "trace",
        _ => "warn",
    };
    let filter = EnvFilter::try_from_env("UMGEN_LOG")
        .unwrap_or_else(|_| EnvFilter::new(format!("warn,umgen={level}")));
    // Only fails when a subscriber is already installed, which leaves logging working.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false)
        .try_init();
}
