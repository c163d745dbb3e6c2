//! Command-line arguments.

use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

mod bench;
mod tokenizer;
pub use bench::*;
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
}

/// Arguments of `umgen generate`.
#[derive(Debug, Args)]
pub struct GenerateArgs {
    /// The bundle (`umgen export`).
    #[arg(long, value_name = "DIR")]
    pub bundle: PathBuf,
    /// History to continue: `DATASET:CLIP` or `DATASET:CLIP:FRAMES` (its first FRAMES frames; default:
    /// the window). Repeat it to continue several clips in one batch (`--scenes` each).
    #[arg(long, value_name = "DATA:CLIP[:FRAMES]", conflicts_with = "from_scratch")]
    pub context: Vec<String>,
    /// Continue COUNT clips of a split, spread evenly over it (`data/sumo-sample:test:64:8`), in one
    /// batch; with `--context`, after those.
    #[arg(
        long,
        value_name = "DATA:SPLIT:COUNT[:FRAMES]",
        conflicts_with = "from_scratch"
    )]
    pub contexts: Option<String>,
    /// Start from nothing: the first frame is generated without history (TAR off).
    #[arg(long)]
    pub from_scratch: bool,
    /// Frames to generate.
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
    /// Scenes generated together (a batch), each with its own random draws.
    #[arg(long, default_value_t = 1)]
    pub scenes: usize,
    /// Output directory: `tokens.json`, `scenes.json`, `rollout.gif` (scene 0).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Also write scene 0's frames as PNGs into the output directory.
    #[arg(long)]
    pub png: bool,
    /// Control file (TOML or JSON), see docs/control.md.
    #[arg(long, value_name = "FILE")]
    pub control: Option<PathBuf>,
    /// Force each context clip's recorded ego actions (the motion it recorded after its context) instead
    /// of the ego module's: `umgen eval` then measures the agents and the rest of the scene given the real
    /// ego motion. The clips need `--frames` more frames after their context; the control file may then
    /// set no ego action.
    #[arg(long)]
    pub recorded_ego: bool,
    /// Frames of history the TAR sees (older ones slide out); default: the history the model was trained
    /// on (`train.frames`), at most 20 and `backbone.max_frames`.
    #[arg(long)]
    pub window: Option<usize>,
    /// Window frames the ego module and the TAR process at once (scenes × window frames; bounds their
    /// memory, the frames drawn do not depend on it).
    #[arg(long, value_name = "FRAMES", default_value_t = umgen::generate::DEFAULT_PASS_FRAMES)]
    pub pass_frames: usize,
    /// How draws on a CUDA device find the top-k ids (the CPU draws on the host).
    #[arg(long, value_enum, default_value = "reduce")]
    pub device_top_k: DeviceTopKArg,
    /// Where the map and image codes are drawn: `auto` draws on the host up to
    /// 16 scenes per batch and on a CUDA device above (the CPU always draws on the host).
    #[arg(long, value_enum, default_value = "auto")]
    pub draw: DrawArg,
    /// Decode map and image codes in speculative blocks of up to K positions, drafted by the TAR heads
    /// and checked by one OAR pass each (same distribution, fewer sequential steps; 0 = off).
    #[arg(long, value_name = "K", default_value_t = 0)]
    pub speculate: usize,
    /// Stop generating after this many minutes (the frame under way is finished) and write the frames
    /// made so far, for machines lent for a fixed time.
    #[arg(long, value_name = "MINUTES", value_parser = tokenizer::positive_minutes)]
    pub time_limit: Option<f64>,
    /// Keep the k most likely ids (0 = all), every modality.
    #[arg(long, default_value_t = 16)]
    pub top_k: usize,
    /// Top-k of one modality instead of `--top-k` (repeatable), e.g. `--top-k-of agent=5`; the authors'
    /// evaluation uses `ego=5`, `map=5`, `agent=5` and 16 for the image.
    #[arg(long = "top-k-of", value_name = "MODALITY=K", value_parser = modality_top_k)]
    pub top_k_of: Vec<(String, usize)>,
    /// Nucleus mass (1 = off), every modality.
    #[arg(long, default_value_t = 1.0)]
    pub top_p: f64,
    /// Softmax temperature, every modality.
    #[arg(long, default_value_t = 1.0)]
    pub temperature: f64,
    /// Seed of the random draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// Arguments of `umgen eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Output of `umgen generate` (`scenes.json`, `meta.json`).
    #[arg(long, value_name = "DIR")]
    pub generated: PathBuf,
    /// The real dataset (ground truth of the context clip; the reference collision rate and initial scenes).
    #[arg(long, value_name = "DIR")]
    pub reference: PathBuf,
    /// Report directory (`report.json`, `report.md`, `l2.png`); default `<generated>/eval`.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Split of the reference data sampled for the real collision rate and initial scenes.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Use every n-th frame of the reference split.
    #[arg(long, default_value_t = 10)]
    pub stride: usize,
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
    /// Stop after this many minutes, with a checkpoint (`--resume` continues), for machines lent for a
    /// fixed time. Checked on logging steps (`train.log_every`).
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
    /// acceleration and repeated displacement against the recorded states.
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

/// `MODALITY=K` of `--top-k-of`.
fn modality_top_k(s: &str) -> Result<(String, usize), String> {
    match s.split_once('=') {
        Some((name, k)) if !name.is_empty() => k
            .parse()
            .map(|k| (name.to_string(), k))
            .map_err(|_| format!("`{s}`: K must be a whole number (0 = all ids)")),
        _ => Err(format!("`{s}`: expected MODALITY=K, e.g. agent=5")),
    }
}

/// Where draws of positions without rules happen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DrawArg {
    /// The host up to [`DrawArg::HOST_MAX_SCENES`] scenes per batch, a CUDA device above.
    Auto,
    /// Always the host: the logits are read back every step.
    Host,
    /// On a CUDA device: top-k, filters and the draw run there, the ids are read back once per frame.
    Device,
}

impl DrawArg {
    /// Largest batch drawn on the host by `auto`. In the eighth session's breakdown (`small`, H200,
    /// batch 1) reading back 8,192 logits and drawing on the host took 0.085 ms a step, the device
    /// draw 2.9 ms (`reduce`) to 5.4 ms (`rounds`); the read-back grows with the batch, the device
    /// draw's kernel count does not.
    pub const HOST_MAX_SCENES: usize = 16;

    /// Whether a batch of `scenes` draws on the device, on a CUDA device or not.
    pub fn on_device(self, cuda: bool, scenes: usize) -> bool {
        cuda && match self {
            Self::Auto => scenes > Self::HOST_MAX_SCENES,
            Self::Host => false,
            Self::Device => true,
        }
    }
}

/// How draws on the GPU find each row's top-k ids.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DeviceTopKArg {
    /// k rounds of argmax, gather and masking (about 3k kernels per draw).
    Rounds,
    /// burn's `argtopk`: one reduction kernel, then a gather.
    Reduce,
}

impl From<DeviceTopKArg> for umgen::generate::DeviceTopK {
    fn from(a: DeviceTopKArg) -> Self {
        match a {
            DeviceTopKArg::Rounds => Self::Rounds,
            DeviceTopKArg::Reduce => Self::Reduce,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::DrawArg;

    #[test]
    fn auto_draws_small_batches_on_the_host_and_the_cpu_never_on_a_device() {
        let max = DrawArg::HOST_MAX_SCENES;
        assert!(!DrawArg::Auto.on_device(true, 1));
        assert!(!DrawArg::Auto.on_device(true, max));
        assert!(DrawArg::Auto.on_device(true, max + 1));
        assert!(DrawArg::Device.on_device(true, 1));
        assert!(!DrawArg::Host.on_device(true, 512));
        for d in [DrawArg::Auto, DrawArg::Host, DrawArg::Device] {
            assert!(!d.on_device(false, 512), "{d:?}");
        }
    }
}
