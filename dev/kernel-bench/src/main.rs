//! `umgen-kernel-bench`: the tools of umgen's kernel developers, kept out of the `umgen` binary users
//! install. Each tool measures one family of training kernels against burn's own operations (agreement of
//! outputs and gradients, time, memory), checks that training stays reproducible, compares kernel settings
//! within one process, profiles the host, or times the parts of a decoding step. They build on the
//! `umgen` command line's library (`umgen_cli`): the same device choice, configs and training steps.

mod alternate;
mod args;
mod attention;
mod decode;
mod flash;
mod host_profile;
mod layers;
mod linear;
mod matmul;
mod repro;
mod train;

use args::{Cli, Command};
use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let args = Cli::parse();
    umgen_cli::run_main(args.verbose, || match args.command {
        Command::Attention(a) => attention::run(&a),
        Command::Matmul(a) => matmul::run(&a),
        Command::Linear(a) => linear::run(&a),
        Command::Layers(a) => layers::run(&a),
        Command::Repro(a) => repro::run(&a),
        Command::Train(a) => train::run(&a),
        Command::Decode(a) => decode::run(&a),
    })
}
