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
    /// Import and inspect datasets.
    #[command(subcommand)]
    Data(DataCommand),
    /// Draw a clip: BEV (map, agents, ego) above the camera view, as a GIF and optionally PNGs.
    Viz(VizArgs),
    /// Measure speed.
    #[command(subcommand)]
    Bench(BenchCommand),
}

/// `umgen data …`
#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Import a SUMO network and FCD trace into a dataset (created or extended).
    Sumo(SumoArgs),
    /// Summarise a dataset: logs, clips, frames and per-modality statistics.
    Info(InfoArgs),
}

/// Arguments of `umgen data sumo`.
#[derive(Debug, Args)]
pub struct SumoArgs {
    /// The SUMO network (`.net.xml`).
    #[arg(long, value_name = "FILE")]
    pub net: PathBuf,
    /// The FCD trace (`sumo --fcd-output`).
    #[arg(long, value_name = "FILE")]
    pub fcd: PathBuf,
    /// Route or additional files defining the vehicle types the trace uses (repeatable).
    #[arg(long = "types", value_name = "FILE")]
    pub types: Vec<PathBuf>,
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Log id (default: the FCD file name up to its first dot).
    #[arg(long)]
    pub name: Option<String>,
    /// Network id (default: the network file name up to its first dot).
    #[arg(long)]
    pub network_name: Option<String>,
    /// Split of the new clips (train, val, test).
    #[arg(long, default_value = "train")]
    pub split: String,
    /// Frames per clip.
    #[arg(long, default_value_t = 40)]
    pub clip_frames: usize,
    /// Shortest clip kept.
    #[arg(long, default_value_t = 21)]
    pub min_frames: usize,
    /// Use every n-th qualifying vehicle as an ego.
    #[arg(long, default_value_t = 1)]
    pub ego_every: usize,
}

/// Arguments of `umgen data info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
}

/// Arguments of `umgen viz`.
#[derive(Debug, Args)]
pub struct VizArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Clip id, or `first`.
    #[arg(long, default_value = "first")]
    pub clip: String,
    /// Output GIF.
    #[arg(long, value_name = "FILE", default_value = "clip.gif")]
    pub out: PathBuf,
    /// Also write one PNG per frame into this directory.
    #[arg(long, value_name = "DIR")]
    pub png_dir: Option<PathBuf>,
    /// First frame.
    #[arg(long, default_value_t = 0)]
    pub start: usize,
    /// Frames to draw (default: to the end of the clip).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Sampling gap between drawn frames.
    #[arg(long, default_value_t = 1)]
    pub gap: usize,
    /// Side of the BEV in pixels (the map covers 128 m).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
}

/// `umgen bench …`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Windows per second read from a dataset (and rendered, with --render).
    Data(BenchDataArgs),
}

/// Arguments of `umgen bench data`.
#[derive(Debug, Args)]
pub struct BenchDataArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Frames per window (T + 1).
    #[arg(long, default_value_t = 21)]
    pub frames: usize,
    /// Sampling gap.
    #[arg(long, default_value_t = 1)]
    pub gap: usize,
    /// Seconds to run each measurement.
    #[arg(long, default_value_t = 3.0)]
    pub seconds: f64,
    /// Also render the map raster and camera image of every frame.
    #[arg(long)]
    pub render: bool,
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
