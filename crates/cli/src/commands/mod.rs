//! One module per subcommand. `bench`, `bench_train` and `train` are public for the developer tools
//! (`dev/kernel-bench`), which run the same steps.

mod agents;
pub mod bench;
mod bench_allreduce;
mod bench_generate;
mod bench_generate_burn;
pub mod bench_train;
mod bench_train_settings;
mod contexts;
mod data;
mod doctor;
mod engine;
mod eval;
mod eval_horizon;
mod eval_map;
mod eval_plot;
mod eval_report;
mod eval_seen;
mod eval_targets;
mod eval_truth;
mod export;
mod frame_map;
mod generate;
mod generate_plan;
mod launch;
mod layout;
mod map_memory;
mod recorded;
mod road;
mod scenes;
mod tokenize;
mod tokenizer;
pub mod train;
mod viz;

use crate::Kinds;
use crate::cli::Command;
pub use launch::guard_parent;

/// Runs a subcommand.
pub fn run(command: Command, kinds: &Kinds) -> anyhow::Result<()> {
    match command {
        Command::Layout(args) => layout::run(&args, kinds),
        Command::Doctor => doctor::run(),
        Command::Data(c) => data::run(c),
        Command::Viz(args) => viz::run(&args, kinds),
        Command::Bench(c) => bench::run(c, kinds),
        Command::Tokenizer(c) => tokenizer::run(c),
        Command::Tokenize(args) => tokenize::run(&args, kinds),
        Command::Train(args) => train::run(&args, kinds),
        Command::Launch(args) => launch::run(&args),
        Command::Export(args) => export::run(&args, kinds),
        Command::Eval(args) => eval::run(&args, kinds),
        Command::Generate(args) => generate::run(&args, kinds),
    }
}
