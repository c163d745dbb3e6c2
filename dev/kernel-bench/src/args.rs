//! Arguments of the kernel developers' tools.

use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;
use umgen_cli::cli::{BenchModelArgs, BenchTrainArgs, ConfigArgs};

/// umgen's kernel developers' tools: the training kernels against burn's operations (agreement and time),
/// reproducibility, kernel settings compared within one process, host profiles, the parts of a decoding
/// step. Users measure with `umgen bench train|generate|data|allreduce`.
#[derive(Debug, Parser)]
#[command(name = "umgen-kernel-bench", version)]
pub struct Cli {
    /// More log output (-v: debug, -vv: trace); `UMGEN_LOG` overrides it.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// The tool to run.
    #[command(subcommand)]
    pub command: Command,
}

/// The tools.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// The backbone's tiled attention against burn's decomposed attention: agreement of outputs and
    /// gradients, forward+backward time and memory, at the shapes of the `small` and `paper` presets.
    Attention(BenchAttentionArgs),
    /// The matrix-product kernels cubecl offers (burn's default and the ones its autotuning chooses
    /// between), each timed and checked against the default on the shapes of the `small` training step.
    Matmul(BenchMatmulArgs),
    /// A linear layer's product, forward and both gradients, on the kernels training can use
    /// (`train.kernels.matmul = "named"`, and `"cublas"` on CUDA) against burn's own path: agreement with burn's
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
    /// `umgen bench train`'s steps with developer hooks: kernel settings taking turns within one process
    /// (`--alternate`), a sampling profile of the host's threads (`--host-profile`).
    Train(TrainArgs),
    /// The parts of one decoding step of the burn decoder timed one by one (input, OAR layers, head over
    /// the largest vocabulary, device draw with each top-k method, host read-back), on a model of random
    /// weights.
    Decode(DecodeArgs),
}

/// Arguments of `umgen-kernel-bench train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// What `umgen bench train` takes.
    #[command(flatten)]
    pub bench: BenchTrainArgs,
    /// Steps take turns between the values of one kernel setting, `KEY=V1,V2[,...]` (e.g.
    /// `train.kernels.attention=flash2,fused`), and each value's median step is printed: a comparison inside one
    /// process, free of the spread between processes. Only settings that leave the run the same alternate
    /// (`train.kernels.matmul`, `train.kernels.attention`, `train.kernels.attention_step`, `train.kernels.attention_block_mib`,
    /// `train.kernels.recompute`, `train.kernels.layer`, `train.kernels.kept_inputs`, `train.kernels.recompute_gelu`, `train.kernels.norm`, `train.kernels.gelu`, `train.kernels.xent`, `train.kernels.stream`, `train.kernels.adamw`,
    /// `train.kernels.launch_thread`, `train.kernels.epilogue`); `--warmup` must cover one step of each value.
    #[arg(long, value_name = "KEY=V1,V2")]
    pub alternate: Option<String>,
    /// Write a sampling profile of the host's threads over the timed steps to this file (collapsed stacks;
    /// builds with the `host-profile` feature).
    #[arg(long, value_name = "FILE")]
    pub host_profile: Option<PathBuf>,
}

/// Arguments of `umgen-kernel-bench decode`.
#[derive(Debug, Args)]
pub struct DecodeArgs {
    /// The config measured, with random weights.
    #[command(flatten)]
    pub model: BenchModelArgs,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Scenes decoded together.
    #[arg(long, default_value_t = 1)]
    pub batch: usize,
}

/// Arguments of `umgen-kernel-bench repro`.
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

/// Arguments of `umgen-kernel-bench layers`.
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

/// Arguments of `umgen-kernel-bench linear`.
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

/// Arguments of `umgen-kernel-bench matmul`.
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

/// Arguments of `umgen-kernel-bench attention`.
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
    /// Loop steps of the fused kernels (`train.kernels.attention_step`: 16, 32 or 64), comma-separated: one fused
    /// row per step (default: the training default).
    #[arg(long, value_delimiter = ',')]
    pub step: Vec<usize>,
    /// Training attention kernels to measure (`train.kernels.attention`), comma-separated: one row each (the tiled
    /// one once per `--block-mib` size, the fused one once per `--step`). Default: `flash2,fused,tiled` on
    /// CUDA, `tiled` on the CPU, which has neither of the others.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub kernels: Vec<AttentionArg>,
    /// flash2's backward passes to measure (`train.kernels.attention_backward`), comma-separated: one flash2
    /// row each. Default: both.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub backward: Vec<BackwardArg>,
}

/// `--backward` values (`train.kernels.attention_backward`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BackwardArg {
    /// Key/value gradients and query gradients in two kernels.
    TwoPass,
    /// All three in one kernel, the queries' gradient added by a bulk reduction (head size 64 on an H100 or
    /// H200).
    OnePass,
}

impl From<BackwardArg> for umgen::ops::kernels::Flash2Backward {
    fn from(a: BackwardArg) -> Self {
        match a {
            BackwardArg::TwoPass => Self::TwoPass,
            BackwardArg::OnePass => Self::OnePass,
        }
    }
}

/// `--kernels` values (`train.kernels.attention`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum AttentionArg {
    /// One cubecl kernel per pass (CUDA).
    Fused,
    /// The tiled passes in burn tensor operations.
    Tiled,
    /// FlashAttention-2 in CUDA C, NVRTC (CUDA; head sizes 32 and 64).
    Flash2,
}

impl From<AttentionArg> for umgen::ops::flash::AttentionKernel {
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
