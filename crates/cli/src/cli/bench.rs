//! Arguments of `umgen bench …`.

use super::DistArgs;
use clap::{Args, Subcommand};
use std::path::PathBuf;

/// `umgen bench …`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Windows per second read from a dataset (and rendered, with --render).
    Data(BenchDataArgs),
    /// Training step time, tokens/s, model FLOPs utilisation and peak memory on random tokens. Under
    /// `umgen launch` it measures data-parallel steps (gradients averaged over the ranks).
    Train(BenchTrainArgs),
    /// All-reduce bandwidth through the process group, run under `umgen launch`.
    Allreduce(BenchAllreduceArgs),
    /// Per-token generation latency and memory as the history grows: the TAR/OAR model against a vanilla
    /// autoregressive transformer of the same width and depth over all frames' tokens (paper Fig. 7).
    Generate(BenchGenerateArgs),
}

/// Arguments of `umgen bench generate`.
#[derive(Debug, Args)]
pub struct BenchGenerateArgs {
    /// The config measured, with random weights.
    #[command(flatten)]
    pub model: BenchModelArgs,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// What decodes: the generation engine, or the burn model (`umgen generate --decoder`).
    #[arg(long, value_enum, default_value = "engine")]
    pub decoder: super::DecoderArg,
    /// The engine's weights and products on a GPU.
    #[arg(long, value_enum, default_value = "auto")]
    pub precision: super::EnginePrecisionArg,
    /// History lengths T (frames); each must fit `backbone.max_frames`.
    #[arg(long, value_delimiter = ',', default_value = "1,20")]
    pub history: Vec<usize>,
    /// Scenes per batch (each batch size is measured at every history length).
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub batch: Vec<usize>,
    /// New frames timed per measurement (the median is reported); a frame of the paper layout takes
    /// seconds with the burn decoder, so a quick look there can ask for 1.
    #[arg(long, default_value_t = 3)]
    pub frames: usize,
    /// Also time a rollout of this many frames at the first batch size, from a history of the first
    /// history length (the window grows, then slides): seconds in all and per frame.
    #[arg(long, value_name = "FRAMES", default_value_t = 0)]
    pub rollout: usize,
    /// Also compare greedy frames (top-k 1) of the engine and of the burn decoder on the same weights and
    /// histories, over this many frames at the first batch size and history length: how many tokens and
    /// frames agree (all of them with `--precision f32`, up to float rounding).
    #[arg(long, value_name = "FRAMES", default_value_t = 0)]
    pub check: usize,
    /// Engine: after the measurements, one more frame at the last batch size and history length with every
    /// operation of its window pass timed (by kind), then each operation of a decoding step timed alone
    /// (replayed 50 times as one graph).
    #[arg(long)]
    pub profile: bool,
    /// Burn decoder: tokens timed per vanilla-AR measurement (0: no vanilla AR).
    #[arg(long, default_value_t = 64)]
    pub tokens: usize,
    /// Burn decoder: how draws on a CUDA device find the top-k ids.
    #[arg(long, value_enum, default_value = "reduce")]
    pub device_top_k: super::DeviceTopKArg,
    /// Burn decoder: where the frames draw (see `umgen generate --draw`).
    #[arg(long, value_enum, default_value = "auto")]
    pub draw: super::DrawArg,
    /// Burn decoder: speculative blocks of up to K positions (0 = off; see `umgen generate`).
    #[arg(long, value_name = "K", default_value_t = 0)]
    pub speculate: usize,
}

/// Arguments of `umgen bench allreduce`.
#[derive(Debug, Args)]
pub struct BenchAllreduceArgs {
    /// `cpu`, or `cuda` (each rank uses the GPU of its `LOCAL_RANK`).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Buffer sizes in MiB.
    #[arg(long, value_delimiter = ',', default_value = "1,16,64,256")]
    pub mib: Vec<f64>,
    /// Timed all-reduces per size (the median is reported).
    #[arg(long, default_value_t = 20)]
    pub iters: usize,
    /// Data-parallel settings.
    #[command(flatten)]
    pub dist: DistArgs,
}

/// Arguments of `umgen bench train`.
#[derive(Debug, Args)]
pub struct BenchTrainArgs {
    /// The config measured, on random tokens.
    #[command(flatten)]
    pub model: BenchModelArgs,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Timed steps (the median is reported).
    #[arg(long, default_value_t = 10)]
    pub steps: usize,
    /// Untimed warm-up steps (kernel compilation and autotuning happen here).
    #[arg(long, default_value_t = 3)]
    pub warmup: usize,
    /// Also time each phase of the step (forward, backward, gradient all-reduce, optimizer) with a device
    /// sync after each; the syncs remove overlap between phases, so the step is timed separately.
    #[arg(long)]
    pub phases: bool,
    /// Peak dense throughput of the device in TFLOP/s, for MFU (default: 989, an H100/H200's bf16).
    #[arg(long, default_value_t = 989.0)]
    pub peak_tflops: f64,
    /// Data-parallel settings.
    #[command(flatten)]
    pub dist: DistArgs,
}

/// The config a benchmark measures: a file or a preset, and overrides (tokenizers are not needed: speed
/// does not depend on them).
#[derive(Debug, Args)]
pub struct BenchModelArgs {
    /// The config whose layout and backbone are measured; default with `--preset`:
    /// `configs/<preset>.toml`.
    #[arg(short, long, value_name = "FILE", required_unless_present = "preset")]
    pub config: Option<PathBuf>,
    /// Override a config key (applied after the preset's).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// The sizes of `torch_umgen.py`'s preset of this name, for side-by-side timing (docs/performance.md):
    /// N = 2199 (60 agents, no boundary tokens), no dropout; `small` batch 4 × T 8, `paper` batch 1 × T 20.
    #[arg(long, value_enum)]
    pub preset: Option<BenchPreset>,
}

/// The reference sizes `umgen bench train --preset` knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchPreset {
    /// D 384, 4 layers per stack, batch 4 × T 8.
    Small,
    /// D 768, the paper's depths, batch 1 × T 20, self-attention layers recomputed (`train.kernels.recompute`).
    Paper,
}

impl BenchPreset {
    /// Its name (also the stem of its config under `configs/`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Small => "small",
            Self::Paper => "paper",
        }
    }

    /// Config overrides that give the PyTorch reference's sizes.
    pub fn overrides(self) -> Vec<String> {
        // The reference checkpoints `paper`'s layers, which do not fit in an H200 otherwise.
        let (batch, frames, recompute) = match self {
            Self::Small => (4, 8, false),
            Self::Paper => (1, 20, true),
        };
        [
            "layout.boundary_tokens=false".to_string(),
            "modality.agent.max_agents=60".into(),
            "backbone.dropout=0.0".into(),
            // The reference's model is the paper's: no agent slots moved ahead.
            "backbone.track=\"\"".into(),
            "backbone.track_accel=false".into(),
            format!("train.batch_size={batch}"),
            format!("train.frames={frames}"),
            format!("train.kernels.recompute={recompute}"),
        ]
        .into()
    }
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
