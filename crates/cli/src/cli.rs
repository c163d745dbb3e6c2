//! Command-line arguments.

use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

mod bench;
mod generate;
mod tokenizer;
pub use bench::*;
pub use generate::*;
pub use tokenizer::*;

/// Train and run UMGen-style multimodal driving-scene generators.
#[derive(Debug, Parser)]
#[command(name = "umgen", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    /// More log output (-v debug, -vv trace). `UMGEN_LOG` (e.g. `umgen=debug`) overrides it. Ranks other
    /// than 0 of a data-parallel job log warnings only, unless `UMGEN_LOG_ALL_RANKS=1`.
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
    /// Train and evaluate the VQ tokenizers of image-like modalities (map, image).
    #[command(subcommand)]
    Tokenizer(TokenizerCommand),
    /// Encode every frame of a dataset with every modality of a config into a token cache.
    Tokenize(TokenizeArgs),
    /// Train the backbone (tokenizing `train.data` first when the token cache is missing). Under
    /// `umgen launch`, torchrun or SLURM, one process per GPU trains data-parallel.
    Train(TrainArgs),
    /// Write a self-contained bundle (weights, tokenizers, manifest) of a training run's newest checkpoint.
    Export(ExportArgs),
    /// Generate scenes with an exported bundle: continue a dataset clip or start from nothing.
    Generate(GenerateArgs),
    /// Measure generated scenes against real data: MMD of agent attributes, collision rate, L2 of ego and
    /// agents against ground truth next to the constant-velocity baseline.
    Eval(EvalArgs),
    /// Start K local ranks of a command (e.g. `train`) with the torchrun variables and supervise them:
    /// if one fails, the others are stopped and the exit code is non-zero.
    Launch(LaunchArgs),
}

/// Arguments of `umgen export`.
#[derive(Debug, Args)]
pub struct ExportArgs {
    /// A run directory (its newest good checkpoint) or one checkpoint directory.
    #[arg(long, value_name = "DIR")]
    pub checkpoint: PathBuf,
    /// The bundle directory to create.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Element type of the exported weights: `f32` or `bf16`.
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// Also write `golden.safetensors`: N windows of random well-formed tokens and the logits this model
    /// computes for them on the CPU, which `python -m umgen_torch.check BUNDLE` compares with its own.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub golden: usize,
    /// Seed of the golden file's tokens.
    #[arg(long, value_name = "SEED", default_value_t = 0, requires = "golden")]
    pub golden_seed: u64,
}

/// Arguments of `umgen launch`.
#[derive(Debug, Args)]
pub struct LaunchArgs {
    /// Processes (ranks) on this node; usually one per GPU.
    #[arg(long, default_value_t = 1)]
    pub nproc_per_node: usize,
    /// Nodes in the job.
    #[arg(long, default_value_t = 1)]
    pub nnodes: usize,
    /// This node's index, `0..nnodes`.
    #[arg(long, default_value_t = 0)]
    pub node_rank: usize,
    /// Host of rank 0 (node 0).
    #[arg(long, default_value = "127.0.0.1")]
    pub master_addr: String,
    /// Rendezvous port on rank 0's host.
    #[arg(long, default_value_t = umgen::dist::DEFAULT_PORT)]
    pub master_port: u16,
    /// The umgen command each rank runs, after `--` (e.g. `-- train --config c.toml --device cuda`).
    #[arg(last = true, required = true)]
    pub command: Vec<String>,
}

/// How ranks of a data-parallel run talk (read by `train`, `tokenizer train` and `bench train`).
#[derive(Debug, Clone, Args)]
pub struct DistArgs {
    /// Seconds after which a dead, stopped or hung rank fails every rank (also the rendezvous timeout).
    #[arg(long, env = "UMGEN_DIST_TIMEOUT", default_value_t = 120)]
    pub dist_timeout: u64,
    /// Collectives: `auto` (NCCL on CUDA, TCP on the CPU), `tcp` or `nccl`.
    #[arg(long, env = "UMGEN_DIST_BACKEND", default_value = "auto")]
    pub dist_backend: String,
}

/// Arguments of `umgen train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// The config (`[backbone]`, `[train]`, modalities).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// `cpu`, or `cuda:N` in builds with the `cuda` feature.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Continue from the newest good checkpoint in `train.out_dir`.
    #[arg(long)]
    pub resume: bool,
    /// Stop after this many minutes, with a checkpoint (`--resume` continues), for jobs with a wall-clock
    /// budget. Checked on logging steps (`train.log_every`).
    #[arg(long, value_name = "MINUTES", value_parser = tokenizer::positive_minutes)]
    pub time_limit: Option<f64>,
    /// Data-parallel settings.
    #[command(flatten)]
    pub dist: DistArgs,
}

/// `umgen data …`
#[derive(Debug, Subcommand)]
pub enum DataCommand {
    /// Import a SUMO network and FCD trace into a dataset (created or extended).
    Sumo(SumoArgs),
    /// Summarise a dataset: logs, clips, frames and per-modality statistics.
    Info(InfoArgs),
    /// How far kinematics alone predicts a split's agents: position errors of constant velocity, constant
    /// acceleration, repeated displacement and constant turn rate against the recorded states.
    Kinematics(KinematicsArgs),
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
    /// SUMO's traffic-light states for the trace (the output of `<timedEvent type="SaveTLSStates">`):
    /// stored beside the log, every frame then lists the signal heads in its view (`extras["signals"]`).
    #[arg(long, value_name = "FILE")]
    pub tls: Option<PathBuf>,
}

/// Arguments of `umgen data info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
}

/// Arguments of `umgen data kinematics`.
#[derive(Debug, Args)]
pub struct KinematicsArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Split whose clips are measured.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Frames ahead, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub horizons: Vec<usize>,
    /// Only agents of this category (`vehicle`, `pedestrian` or `cyclist`); every agent by default.
    #[arg(long)]
    pub category: Option<String>,
}

/// Arguments of `umgen viz`.
#[derive(Debug, Args)]
pub struct VizArgs {
    /// Dataset directory.
    #[arg(long, value_name = "DIR", required_unless_present = "generated")]
    pub data: Option<PathBuf>,
    /// Or: an output directory of `umgen generate` (its tokens are decoded with its bundle, context frames
    /// included).
    #[arg(long, value_name = "DIR", conflicts_with = "data")]
    pub generated: Option<PathBuf>,
    /// Which generated scene (with `--generated`).
    #[arg(long, default_value_t = 0)]
    pub scene: usize,
    /// With `--generated`: the bundle to decode its tokens with, in place of the one its `meta.json`
    /// names (an output brought from another machine); it must have the layout the tokens were drawn in.
    #[arg(long, value_name = "DIR", requires = "generated")]
    pub bundle: Option<PathBuf>,
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
    /// With `--data`: also draw what this config's modalities mark on the BEV (a plug-in's traffic lights,
    /// say). A generated scene's bundle names its modalities itself.
    #[arg(long, value_name = "FILE", conflicts_with = "generated")]
    pub config: Option<PathBuf>,
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
