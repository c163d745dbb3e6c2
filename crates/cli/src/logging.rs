//! Logging setup: `tracing` to stderr, filtered by `UMGEN_LOG` or the `-v` count.

use std::io::IsTerminal;
use tracing_subscriber::EnvFilter;

/// Installs the global subscriber. Without `UMGEN_LOG`, umgen logs at info (debug with `-v`, trace with
/// `-vv`) and dependencies at warn.
pub fn init(verbose: u8) {
    let level = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
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
