//! Arguments of `umgen bench …`.

use super::{ConfigArgs, DistArgs};
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
    /// The backbone's tiled attention against burn's decomposed attention: agreement of outputs and
    /// gradients, forward+backward time and memory, at the shapes of the `small` and `paper` presets.
    Attention(BenchAttentionArgs),
    /// The matrix-product kernels cubecl offers (burn's default and the ones its autotuning chooses
    /// between), each timed and checked against the default on the shapes of the `small` training step.
    Matmul(BenchMatmulArgs),
    /// A linear layer's product, forward and both gradients, on the kernels training can use
    /// (`train.matmul = "named"`, and `"cublas"` on CUDA) against burn's own path: agreement with burn's
    /// f32 result, and time.
    Linear(BenchLinearArgs),
    /// The layer norm, the TAR's attention over time, the cross-entropy and an AdamW step as training
    /// computes them (on CUDA, umgen's kernels) against burn's operations: agreement of outputs and
    /// gradients, and time.
    Layers(BenchLayersArgs),
    /// Trains a few steps from one seed several times in one process and reports the first step at which
    /// a run's losses or gradient norm leave the first run's, and whether the final weights agree: kernel
    /// changes must keep training reproducible, and a race between streams shows up here as a run that
    /// leaves the others.
    Repro(BenchReproArgs),
}

/// Arguments of `umgen bench repro`.
#[derive(Debug, Args)]
pub struct BenchReproArgs {
    /// The config trained (its token cache is made from `train.data` if missing, as `umgen train` does).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Runs from the same seed (two or more).
    #[arg(long, default_value_t = 4)]
    pub runs: usize,
    /// Steps each run trains.
    #[arg(long, default_value_t = 20)]
    pub steps: u64,
    /// Steps between the read-outs compared (each read-out waits for the device, which changes how far
    /// the host runs ahead of it).
    #[arg(long, default_value_t = 1)]
    pub log_every: u64,
    /// Largest relative difference from the first run that still counts as agreeing (0: bit for bit).
    #[arg(long, default_value_t = 0.0)]
    pub tolerance: f64,
}

/// Arguments of `umgen bench layers`.
#[derive(Debug, Args)]
pub struct BenchLayersArgs {
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Activation `[B, T, N, D]` (windows, frames, tokens a frame, width). Default: the `small` preset's.
    #[arg(long, value_delimiter = ',', default_value = "4,8,2199,384")]
    pub shape: Vec<usize>,
    /// Attention heads (head size D / heads).
    #[arg(long, default_value_t = 6)]
    pub heads: usize,
    /// Vocabulary of the cross-entropy's logits (`[T · N, vocab]`). Default: the map and image heads'.
    #[arg(long, default_value_t = 8192)]
    pub vocab: usize,
    /// Timed forward+backward passes per path (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub iters: usize,
}

/// Arguments of `umgen bench linear`.
#[derive(Debug, Args)]
pub struct BenchLinearArgs {
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Products as `MxKxN` (`x: [M, K]`, `w: [K, N]`), comma-separated. Default: the `small` step's
    /// attention projection, MLP up and down (M = 4 · 8 · 2199 tokens) and the map head (8192 codes).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "70368x384x384,70368x384x1536,70368x1536x384,32768x384x8192"
    )]
    pub shapes: Vec<String>,
    /// Number formats of the products (`backbone.precision`), comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "f32,bf16")]
    pub dtypes: Vec<PrecisionArg>,
    /// Timed forward+backward passes per path (the median is reported).
    #[arg(long, default_value_t = 10)]
    pub iters: usize,
}

/// Arguments of `umgen bench matmul`.
#[derive(Debug, Args)]
pub struct BenchMatmulArgs {
    /// `cuda:N` (the kernels measured are CUDA's).
    #[arg(long, default_value = "cuda:0")]
    pub device: String,
    /// Products as `[BATCHx]MxKxN`, comma-separated. Default: the `small` step's (M = 4 · 8 · 2199 tokens):
    /// QKV and MLP-up projections, MLP-down, the MLP-up weight gradient, the map head (8192 codes), and
    /// attention scores and values (32 sequences × 6 heads).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "70368x384x1152,70368x384x1536,70368x1536x384,384x70368x1536,32768x384x8192,192x2199x64x2199,192x2199x2199x64"
    )]
    pub shapes: Vec<String>,
    /// Number formats of operands and output, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "f32,bf16")]
    pub dtypes: Vec<PrecisionArg>,
    /// Only kernels whose printed name contains one of these, comma-separated (default: all).
    #[arg(long, value_delimiter = ',')]
    pub kernels: Vec<String>,
    /// Timed launches per kernel and shape (the median is reported).
    #[arg(long, default_value_t = 10)]
    pub iters: usize,
    /// Starts no new measurement after this many seconds; rows print as they finish.
    #[arg(long, default_value_t = 600.0)]
    pub seconds: f64,
}

/// Arguments of `umgen bench attention`.
#[derive(Debug, Args)]
pub struct BenchAttentionArgs {
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Cases as `SEQS×HEADS×LQ×LK×DH` with a trailing `c` for causal, comma-separated (default: the OAR and
    /// spatial-TAR attention of `--preset small`, the OAR of `--preset paper`, the temporal TAR of `small`).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "32x6x2199x2199x64c,32x6x2199x2199x64,20x12x2199x2199x64c,70352x6x8x8x64c"
    )]
    pub cases: Vec<String>,
    /// Timed forward+backward passes per case and path (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub iters: usize,
    /// Number format of the tiled path's matrix products (the decomposed reference stays f32).
    #[arg(long, value_enum, default_value = "f32")]
    pub precision: PrecisionArg,
    /// Instead, time cubecl's fused flash-attention forward kernels (CUDA) against burn's decomposed forward
    /// pass, with their agreement: whether a fused forward would pay in training.
    #[arg(long)]
    pub flash: bool,
    /// Sizes in MiB that one query block's scores may take in the tiled path, comma-separated: one row per
    /// size (default: the training default, 1024).
    #[arg(long, value_delimiter = ',')]
    pub block_mib: Vec<usize>,
    /// Loop steps of the fused kernels (`train.attention_step`: 16, 32 or 64), comma-separated: one fused
    /// row per step (default: the training default).
    #[arg(long, value_delimiter = ',')]
    pub step: Vec<usize>,
    /// Training attention kernels to measure (`train.attention`), comma-separated: one row each (the tiled
    /// one once per `--block-mib` size, the fused one once per `--step`). Default: `flash2,fused,tiled` on
    /// CUDA, `tiled` on the CPU, which has neither of the others.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub kernels: Vec<AttentionArg>,
}

/// `--kernels` values (`train.attention`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum AttentionArg {
    /// One cubecl kernel per pass (CUDA).
    Fused,
    /// The tiled passes in burn tensor operations.
    Tiled,
    /// FlashAttention-2 in CUDA C, NVRTC (CUDA; head sizes 32 and 64).
    Flash2,
}

impl From<AttentionArg> for umgen::backbone::flash::AttentionKernel {
    fn from(a: AttentionArg) -> Self {
        match a {
            AttentionArg::Fused => Self::Fused,
            AttentionArg::Tiled => Self::Tiled,
            AttentionArg::Flash2 => Self::Flash2,
        }
    }
}

/// `--precision` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PrecisionArg {
    /// f32 (TF32 on CUDA tensor cores).
    F32,
    /// bf16 operands, f32 results.
    Bf16,
}

impl PrecisionArg {
    /// The value as written on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        }
    }
}

impl From<PrecisionArg> for umgen::backbone::Precision {
    fn from(p: PrecisionArg) -> Self {
        match p {
            PrecisionArg::F32 => Self::F32,
            PrecisionArg::Bf16 => Self::Bf16,
        }
    }
}

/// Arguments of `umgen bench generate`.
#[derive(Debug, Args)]
pub struct BenchGenerateArgs {
    /// The config whose layout and backbone are measured (random weights; tokenizers are not needed);
    /// default with `--preset`: `configs/<preset>.toml`.
    #[arg(short, long, value_name = "FILE", required_unless_present = "preset")]
    pub config: Option<PathBuf>,
    /// Override a config key (applied after the preset's).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// The sizes of `torch_umgen.py`'s preset of this name (N = 2199: 60 agents, no boundary tokens), for
    /// side-by-side timing with its `infer-scaling` and `infer-graph`.
    #[arg(long, value_enum)]
    pub preset: Option<BenchPreset>,
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
    /// Burn decoder: also time the parts of a decoding step one by one (input, OAR layers, head, device
    /// draw with each top-k method, host read-back), at the first history length.
    #[arg(long)]
    pub breakdown: bool,
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
    /// The config whose layout and backbone are measured (tokenizers are not needed); default with
    /// `--preset`: `configs/<preset>.toml`.
    #[arg(short, long, value_name = "FILE", required_unless_present = "preset")]
    pub config: Option<PathBuf>,
    /// Override a config key (applied after the preset's).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// The sizes of `torch_umgen.py`'s preset of this name, for side-by-side timing (docs/performance.md):
    /// N = 2199 (60 agents, no boundary tokens), no dropout; `small` batch 4 × T 8, `paper` batch 1 × T 20.
    #[arg(long, value_enum)]
    pub preset: Option<BenchPreset>,
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
    /// Steps take turns between the values of one kernel setting, `KEY=V1,V2[,...]` (e.g.
    /// `train.attention=flash2,fused`), and each value's median step is printed: a comparison inside one
    /// process, free of the spread between processes. Only settings that leave the run the same alternate
    /// (`train.matmul`, `train.attention`, `train.attention_step`, `train.attention_block_mib`,
    /// `train.recompute`, `train.norm`, `train.gelu`, `train.xent`, `train.kernel_stream`, `train.adamw`,
    /// `train.launch_thread`); `--warmup` must cover one step of each value.
    #[arg(long, value_name = "KEY=V1,V2")]
    pub alternate: Option<String>,
    /// Data-parallel settings.
    #[command(flatten)]
    pub dist: DistArgs,
}

/// The reference sizes `umgen bench train --preset` knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchPreset {
    /// D 384, 4 layers per stack, batch 4 × T 8.
    Small,
    /// D 768, the paper's depths, batch 1 × T 20, self-attention layers recomputed (`train.recompute`).
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
            format!("train.recompute={recompute}"),
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
