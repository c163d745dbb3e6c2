//! One module per subcommand.

mod doctor;
mod layout;

use crate::cli::Command;

/// Runs a subcommand.
pub fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Layout(args) => layout::run(&args),
        Command::Doctor => doctor::run(),
    }
}
