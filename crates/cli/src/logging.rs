//! Logging setup: `tracing` to stderr, filtered by `UMGEN_LOG` or the `-v` count.

use std::io::IsTerminal;
use tracing_subscriber::EnvFilter;

/// Installs the global subscriber. Without `UMGEN_LOG`, umgen logs at info (debug with `-v`, trace with
/// `-vv`) and dependencies at warn. Ranks other than 0 of a data-parallel job only warn, so progress is
/// printed once, also when `UMGEN_LOG` is set (launchers pass one environment to every rank);
/// `UMGEN_LOG_ALL_RANKS=1` applies `UMGEN_LOG` and `-v` to them too, for debugging one rank.
pub fn init(verbose: u8) {
    let rank = std::env::var("RANK")
        .or_else(|_| std::env::var("SLURM_PROCID"))
        .ok()
        .and_then(|r| r.parse::<usize>().ok())
        .unwrap_or(0);
    let all_ranks = std::env::var("UMGEN_LOG_ALL_RANKS").is_ok_and(|v| v == "1");
    let lead = rank == 0 || all_ranks;
    let level = match (lead, verbose) {
        (true, 0) => "info",
        (true, 1) => "debug",
        (true, _) => "trace",
        (false, _) => "warn",
    };
    let filter = match EnvFilter::try_from_env("UMGEN_LOG") {
        Ok(f) if lead => f,
        _ => EnvFilter::new(format!("warn,umgen={level}")),
    };
    // Only fails when a subscriber is already installed, which leaves logging working.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false)
        .try_init();
}
