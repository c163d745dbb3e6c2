//! Entry point of the `umgen` binary: parse the command line, set up logging, run the command, and turn
//! errors into a message on stderr and a non-zero exit code.

use clap::Parser;
use std::io::Write;
use std::process::ExitCode;
use umgen_cli::{cli, commands, logging};

fn main() -> ExitCode {
    let args = cli::Cli::parse();
    logging::init(args.verbose);
    #[cfg(feature = "cuda")]
    if let Some(dir) = umgen_cli::device::init_kernel_cache() {
        tracing::debug!("compiled CUDA kernels are kept in {}", dir.display());
    }
    commands::guard_parent();
    match commands::run(args.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            // The whole cause chain on one line; nothing else to do if stderr is gone.
            let _ = writeln!(std::io::stderr(), "error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
