//! Command-line arguments.

use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

/// Train and run UMGen-style multimodal driving-scene generators.
#[derive(Debug, Parser)]
#[command(name = "umgen", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    /// More log output (-v debug, -vv trace). `UMGEN_LOG` (e.g. `umgen=debug`) overrides it.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Print the frame layout of a config: each modality's offset, tokens and vocabulary, and N.
    Layout(LayoutArgs),
    /// Check this machine for what GPU runs need (CUDA driver, NVRTC, NCCL).
    Doctor,
}

/// A config file and overrides, shared by every command that reads a config.
#[derive(Debug, Args)]
pub struct ConfigArgs {
    /// TOML config file (see configs/).
    #[arg(short, long, value_name = "FILE")]
    pub config: PathBuf,
    /// Override a config key, e.g. `--set train.steps=60` (repeatable; applied after `UMGEN__…` env vars).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

/// Arguments of `umgen layout`.
#[derive(Debug, Args)]
pub struct LayoutArgs {
    /// The config.
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}
