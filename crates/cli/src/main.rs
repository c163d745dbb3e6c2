//! Entry point of the `umgen` binary: the stock commands and modality kinds ([`umgen_cli::App`]).

use std::process::ExitCode;

fn main() -> ExitCode {
    umgen_cli::App::new().run()
}
