//! Arguments of `umgen generate` and `umgen eval`, and the draw settings they use.

use super::tokenizer;
use clap::Args;
use std::path::PathBuf;

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
    /// Generate even when control entries cannot apply, in whole or in part (past `--frames`, a slot the
    /// model lacks, ego motion for a model without an ego action): each is named in a warning and left
    /// out. Without it they are an error.
    #[arg(long)]
    pub allow_partial_control: bool,
    /// Force each context clip's recorded ego actions (the motion it recorded after its context) instead
    /// of the ego module's: `umgen eval` then measures the agents and the rest of the scene given the real
    /// ego motion. The clips need `--frames` more frames after their context; the control file may then
    /// set no ego action.
    #[arg(long)]
    pub recorded_ego: bool,
    /// Place these modalities (layout labels, comma-separated or repeated: `--recorded lights`,
    /// `--recorded map,image`) as each context clip recorded them after its context, instead of drawing
    /// them: the rest of each frame is generated given them (the agents given the real traffic lights,
    /// say). The clips need `--frames` more frames after their context. The ego action's modality is
    /// `--recorded-ego`; the agents' cannot be combined with a control file's agents.
    #[arg(long, value_name = "MODALITY")]
    pub recorded: Vec<String>,
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
    /// made so far, for jobs with a wall-clock budget.
    #[arg(long, value_name = "MINUTES", value_parser = tokenizer::positive_minutes)]
    pub time_limit: Option<f64>,
    /// Keep the k most likely ids (0 = all), every modality. At an agent slot's first token pad keeps
    /// its untruncated probability and the values among the k share the rest, so that agents enter and
    /// leave at the model's rate (docs/control.md).
    #[arg(long, default_value_t = 16)]
    pub top_k: usize,
    /// Top-k of one modality instead of `--top-k` (repeatable), e.g. `--top-k-of agent=5`; the authors'
    /// evaluation uses `ego=5`, `map=5`, `agent=5` and 16 for the image.
    #[arg(long = "top-k-of", value_name = "MODALITY=K", value_parser = modality_top_k)]
    pub top_k_of: Vec<(String, usize)>,
    /// Nucleus mass (1 = off), every modality.
    #[arg(long, default_value_t = 1.0)]
    pub top_p: f64,
    /// Nucleus mass of one modality instead of `--top-p` (repeatable), e.g. `--top-p-of agent=0.8`
    /// with `--top-k-of agent=64`: the agents' values keep the modes a top-5 list cuts away
    /// (docs/control.md).
    #[arg(long = "top-p-of", value_name = "MODALITY=P", value_parser = modality_top_p)]
    pub top_p_of: Vec<(String, f64)>,
    /// Cut one modality's nucleus from the ids after its most likely one, which keeps its own
    /// probability (repeatable), e.g. `--top-p-of agent=0.8 --top-p-rest-of agent`: a standing agent
    /// drives off at the model's rate instead of never (docs/control.md).
    #[arg(long = "top-p-rest-of", value_name = "MODALITY")]
    pub top_p_rest_of: Vec<String>,
    /// Which boxes a new agent must clear: every old agent of the frame (`frame`), or only the boxes
    /// decoded before it, as the official code does (`before`: an old agent in a later slot may stand
    /// on it). docs/control.md.
    #[arg(long, value_enum, default_value = "frame")]
    pub new_agent_rule: NewAgentRule,
    /// Empty each vehicle entering a frame (its slot empty in the frame before) whose centre lies off
    /// the drivable layers of the map the frame's own codes decode to: the road rule (docs/control.md).
    #[arg(long)]
    pub entering_on_road: bool,
    /// Hold each scene's map fixed in the world: ground the context or an earlier frame showed keeps
    /// its map, and only new ground is drawn. Each frame is drawn twice (docs/control.md).
    #[arg(long)]
    pub map_memory: bool,
    /// Softmax temperature, every modality.
    #[arg(long, default_value_t = 1.0)]
    pub temperature: f64,
    /// Seed of the random draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `cpu`, or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// What decodes the frames.
    #[arg(long, value_enum, default_value = "auto")]
    pub decoder: DecoderArg,
    /// The generation engine's weights and products on a GPU.
    #[arg(long, value_enum, default_value = "auto")]
    pub precision: EnginePrecisionArg,
}

/// Which boxes a new agent must clear (`GroupBoxes::whole_frame`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum NewAgentRule {
    /// Every old agent of the frame and the boxes decoded before it.
    Frame,
    /// The boxes decoded before it (the ego's first), as the official code.
    Before,
}

/// What decodes the frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DecoderArg {
    /// The engine on a GPU, burn on the CPU.
    Auto,
    /// The generation engine: a fixed program of kernels over buffers allocated once, each decoding step
    /// one replayed CUDA graph on a GPU (the host executor on the CPU).
    Engine,
    /// The burn model, one operation at a time (`--speculate`, `--draw` and `--device-top-k` are its
    /// settings).
    Burn,
}

impl DecoderArg {
    /// Whether the engine decodes on `cuda` (a GPU) or not.
    pub fn engine(self, cuda: bool) -> bool {
        match self {
            Self::Auto => cuda,
            Self::Engine => true,
            Self::Burn => false,
        }
    }
}

/// The engine's number format on a GPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum EnginePrecisionArg {
    /// bf16 on a GPU (f32 on the CPU).
    Auto,
    /// Weights and product operands in bf16, f32 accumulation, residual streams, norms, softmax and logits:
    /// half the memory, the tensor cores.
    Bf16,
    /// Everything f32: greedy frames are the burn decoder's on the CPU (on CUDA burn's f32 products run
    /// as TF32, so near-tie tokens can differ).
    F32,
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
    /// The bundle to decode the tokens with, in place of the one `meta.json` names (an output brought
    /// from another machine); it must have the layout the tokens were drawn in.
    #[arg(long, value_name = "DIR")]
    pub bundle: Option<PathBuf>,
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

fn modality_top_p(s: &str) -> Result<(String, f64), String> {
    match s.split_once('=') {
        Some((name, p)) if !name.is_empty() => match p.parse::<f64>() {
            Ok(p) if p > 0.0 && p <= 1.0 => Ok((name.to_string(), p)),
            _ => Err(format!("`{s}`: P must be a number in (0, 1] (1 = off)")),
        },
        _ => Err(format!("`{s}`: expected MODALITY=P, e.g. agent=0.8")),
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
    /// Largest batch drawn on the host by `auto`. In `umgen-kernel-bench decode` (`small`, H200,
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
