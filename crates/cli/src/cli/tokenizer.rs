//! Arguments of `umgen tokenizer …` and `umgen tokenize`.

use super::{ConfigArgs, DistArgs};
use clap::{Args, Subcommand};
use std::path::PathBuf;

/// `umgen tokenizer …`
#[derive(Debug, Subcommand)]
pub enum TokenizerCommand {
    /// Train a modality's VQ tokenizer on rasters rendered from a dataset.
    Train(TokenizerTrainArgs),
    /// Measure a tokenizer's reconstructions (map: IoU per layer; image: PSNR) and draw some.
    Eval(TokenizerEvalArgs),
}

/// Which tokenizer, and the data it is trained or measured on (shared by `tokenizer train` and `eval`).
#[derive(Debug, Args)]
pub struct TokenizerTarget {
    /// The config (its `[modality.<name>]` table sets the architecture and `vq_train`).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Which modality's tokenizer (a `map` or `image` kind).
    #[arg(long)]
    pub modality: String,
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
}

/// Arguments of `umgen tokenizer train`.
#[derive(Debug, Args)]
pub struct TokenizerTrainArgs {
    /// Config, modality and dataset.
    #[command(flatten)]
    pub target: TokenizerTarget,
    /// Run directory (checkpoints, TensorBoard, the tokenizer); default `runs/tokenizer-<modality>`.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Split whose frames are used.
    #[arg(long, default_value = "train")]
    pub split: String,
    /// Use every n-th frame of each clip.
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Stop after this many minutes of training (after a checkpoint; the tokenizer is written and a later
    /// run with the same `--out` resumes), for jobs with a wall-clock budget.
    #[arg(long, value_name = "MINUTES", value_parser = positive_minutes)]
    pub time_limit: Option<f64>,
    /// `cpu`, or `cuda:N` in builds with the `cuda` feature (`cuda` under a launcher: the GPU of
    /// `LOCAL_RANK`).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Data-parallel settings (under `umgen launch`, torchrun or SLURM).
    #[command(flatten)]
    pub dist: DistArgs,
}

/// Arguments of `umgen tokenizer eval`.
#[derive(Debug, Args)]
pub struct TokenizerEvalArgs {
    /// Config, modality and dataset.
    #[command(flatten)]
    pub target: TokenizerTarget,
    /// Tokenizer directory (default: the config's `tokenizer`).
    #[arg(long, value_name = "DIR")]
    pub tokenizer: Option<PathBuf>,
    /// Split to evaluate on.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Frames to evaluate, spread evenly over the split.
    #[arg(long, default_value_t = 256)]
    pub frames: usize,
    /// Directory for `report.json` and input | reconstruction pictures (default: the tokenizer's `eval`).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// Arguments of `umgen tokenize`.
#[derive(Debug, Args)]
pub struct TokenizeArgs {
    /// The config (every modality needs its tokenizer).
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Dataset directory.
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Token cache directory.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Only this split.
    #[arg(long)]
    pub split: Option<String>,
    /// Threads (default: all cores on the CPU; 2 per GPU, since each thread keeps its own device
    /// stream and memory pool).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Where VQ tokenizers run: `cpu`, `cuda:N`, or several devices separated by commas
    /// (`cuda:0,cuda:1,cuda:2,cuda:3`), over which the threads are spread.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// A positive, finite number of minutes.
pub(crate) fn positive_minutes(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(m) if m.is_finite() && m > 0.0 => Ok(m),
        _ => Err(format!("`{s}` is not a positive number of minutes")),
    }
}
