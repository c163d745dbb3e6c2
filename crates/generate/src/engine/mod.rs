//! The generation engine: the backbone's generation forward pass as a fixed program of operations
//! (`umgen_cuda::ops`) over buffers allocated once, run by an [`Exec`]utor: on a GPU
//! (`umgen_cuda::gpu::CudaExec`, with the `cuda` feature) or on the host ([`HostExec`]).
//!
//! A frame is made in two parts, for up to [`GEMV_ROWS`] scenes at a time:
//!
//! 1. The window pass (`window.rs`): the history's embeddings, the ego module (its logits read back once and
//!    drawn on the host, as the burn decoder draws them), AMA, the tracked slots, the TAR over the window,
//!    and the TAR heads' logits at the positions a keep rule may redraw. Products of many rows go to cuBLAS;
//!    the window's length only changes launch sizes, so nothing is compiled after start-up.
//! 2. The decoding step (`step.rs`), once per position: the embedding of the previous token, every OAR
//!    layer over its key/value cache, the head of the position's modality and the draw with the frame's
//!    token rules, one matrix-vector kernel per product and nothing read back. The position, the tokens,
//!    the caches and the rules' state live in device buffers, so a GPU executor replays the step as one CUDA
//!    graph per modality and the host only queues N launches. The frame's tokens are read back at its end.
//!
//! Draws use Philox counters (seed, scene, position, frame) rather than the host's generator, so the
//! frames have the distribution the burn decoder draws from, and greedy frames are the same frames.

mod buffers;
mod ego;
mod host;
mod host_draw;
mod host_frame;
mod host_ops;
mod step;
mod tar;
mod weights;
mod window;

use crate::error::{GenerateError, Result};
use crate::rules::{FrameControl, FrameRules, check_frame};
use crate::sampling::Sampling;
pub use host::HostExec;
pub use tar::track_op;

use buffers::{Caps, DecodeBufs, Tables, WindowBufs, alloc};
use rand::{SeedableRng, rngs::StdRng};
use std::collections::HashMap;
use umgen_backbone::{PlainBackbone, Slot};
use umgen_cuda::ops::{DRAW_KMAX, Exec, GEMV_ROWS, MAX_HEAD, Op, ROWS_MAX_SPLITS, ROWS_SPLIT};
use weights::Weights;

/// Rows of the MLP's hidden activation held at once in the window pass (its products run in slices of
/// this many rows).
const HIDDEN_ROWS: usize = 16_384;

/// Sizes of the model.
#[derive(Debug, Clone)]
struct Layout {
    n: usize,
    d: usize,
    e: usize,
    heads: usize,
    dh: usize,
    hidden: usize,
    slots: Vec<Slot>,
    seg_of: Vec<usize>,
    spec: umgen_backbone::BackboneSpec,
}

/// What the working buffers' sizes depend on beyond the layout: the model's parts.
#[derive(Debug, Clone)]
struct Sizes {
    /// OAR layers.
    layers: usize,
    /// The ego module's query count, action block length and head width.
    ego: Option<(usize, usize, usize)>,
    /// Whether the tracked slots are moved (the spec's track and the model's projections).
    track: bool,
}

impl Sizes {
    fn of(m: &PlainBackbone) -> Self {
        Self {
            layers: m.oar.len(),
            ego: m.ego.as_ref().map(|g| (g.q, g.block[1], g.head.d_out)),
            track: m.track.is_some(),
        }
    }
}

/// What the engine was asked to do and how.
#[derive(Debug, Clone)]
pub struct EngineSettings {
    /// Sampling per segment.
    pub sampling: Vec<Sampling>,
    /// Most history frames the TAR sees.
    pub window: usize,
    /// Seed of the draws.
    pub seed: u64,
    /// Window frames per pass of the ego module and the TAR (at least one scene's window).
    pub pass_frames: usize,
}

/// Generates frames with a backbone's weights on an executor.
pub struct Engine<X: Exec> {
    x: X,
    w: Weights,
    lay: Layout,
    settings: EngineSettings,
    rng: StdRng,
    key: [u32; 2],
    frames: u32,
    group: usize,
    chunk: usize,
    win: WindowBufs,
    dec: DecodeBufs,
    steps: HashMap<(usize, usize), Vec<Op>>,
    generation: u64,
    new_agents: (u64, u64),
    /// The frame's keep entries: position and segment, in keep order.
    keeps: Vec<(usize, usize)>,
    /// What the buffers are sized from.
    sizes: Sizes,
    /// Whether to wait for the device after each part of a frame and add up its time.
    timed: bool,
    times: Times,
    /// The window pass's operations' seconds and counts by name, while profiling (`Engine::profiled`).
    profile: Option<std::collections::BTreeMap<String, (f64, u64)>>,
}

/// Seconds spent in each part of the frames made while timing ([`Engine::timed`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Times {
    /// The window pass (ego module, TAR, keep logits) and the frame's tables.
    pub window: f64,
    /// The decoding steps and the frame's read-back.
    pub decode: f64,
    /// Frames made.
    pub frames: u64,
    /// Decoding steps run (positions × scene groups).
    pub steps: u64,
}

impl<X: Exec> Engine<X> {
    /// An engine for `model` on `x`; refuses sizes and sampling settings the kernels do not take.
    pub fn new(mut x: X, model: &PlainBackbone, settings: EngineSettings) -> Result<Self> {
        let spec = &model.spec;
        let (n, d, heads) = (spec.n, model.d, model.heads);
        if settings.sampling.len() != spec.segments.len() {
            return Err(GenerateError::Settings(format!(
                "{} sampling settings for {} modalities",
                settings.sampling.len(),
                spec.segments.len()
            )));
        }
        for (s, seg) in settings.sampling.iter().zip(&spec.segments) {
            s.validate(&format!("sampling.{}", seg.label))?;
            if (s.top_k == 0 || s.top_k > DRAW_KMAX) && s.top_p < 1.0 {
                return Err(GenerateError::Settings(format!(
                    "sampling.{}: top-p {} with top-k {}: the engine draws top-p from a top-k of 1..={DRAW_KMAX}",
                    seg.label, s.top_p, s.top_k
                )));
            }
        }
        if settings.window == 0 || settings.window > model.time.len() / d.max(1) {
            return Err(GenerateError::Settings(format!(
                "window = {}: the model takes 1..={} frames",
                settings.window,
                model.time.len() / d.max(1)
            )));
        }
        let dh = d / heads.max(1);
        if heads == 0 || dh * heads != d || dh > MAX_HEAD || !dh.is_multiple_of(4) {
            return Err(GenerateError::Settings(format!(
                "{heads} heads of width {d}: the engine's attention takes head sizes that are multiples of 4 up to {MAX_HEAD}"
            )));
        }
        // A query's keys are split over at most ROWS_MAX_SPLITS blocks of ROWS_SPLIT.
        if n > ROWS_SPLIT * ROWS_MAX_SPLITS {
            return Err(GenerateError::Settings(format!(
                "N = {n} tokens a frame: the engine's attention takes frames of up to {} tokens",
                ROWS_SPLIT * ROWS_MAX_SPLITS
            )));
        }
        let hidden = model
            .oar
            .first()
            .or(model.tar.first().map(|l| &l.0))
            .map_or(4 * d, |l| l.mlp.fc.d_out);
        let mut seg_of = vec![0; n];
        for (s, seg) in spec.segments.iter().enumerate() {
            seg_of[seg.block_start..seg.block_start + seg.block_len].fill(s);
        }
        let slots = (0..n)
            .map(|p| {
                let s = seg_of[p];
                let seg = &spec.segments[s];
                if p < seg.offset {
                    Slot::Start(s)
                } else if p >= seg.offset + seg.tokens {
                    Slot::End(s)
                } else {
                    Slot::Content(s, p - seg.offset)
                }
            })
            .collect();
        let lay = Layout {
            n,
            d,
            e: model.embed.e,
            heads,
            dh,
            hidden,
            slots,
            seg_of,
            spec: spec.clone(),
        };
        let started = std::time::Instant::now();
        let w = Weights::upload(&mut x, model)?;
        tracing::info!(
            "weights on the executor in {:.1} s ({:.2} GiB)",
            started.elapsed().as_secs_f64(),
            x.bytes() as f64 / (1u64 << 30) as f64
        );
        // Sized for one scene; `fit` grows them to the batch a frame brings (up to GEMV_ROWS scenes).
        let (group, chunk) = (1, 1);
        let sizes = Sizes::of(model);
        let win = WindowBufs::new(&mut x, &lay, &sizes, chunk, settings.window)?;
        let dec = DecodeBufs::new(&mut x, &lay, &sizes, group)?;
        let seed = settings.seed;
        Ok(Self {
            x,
            w,
            lay,
            rng: StdRng::seed_from_u64(seed),
            key: [seed as u32, (seed >> 32) as u32 ^ 0x5bd1_e995],
            settings,
            frames: 0,
            group,
            chunk,
            win,
            dec,
            steps: HashMap::new(),
            generation: 0,
            new_agents: (0, 0),
            keeps: Vec::new(),
            sizes,
            timed: false,
            times: Times::default(),
            profile: None,
        })
    }

    /// The next frame `[m][N]` of each of `m` scenes from their histories `[m][t][N]` (all of one length;
    /// `t = 0` makes initial scenes without TAR), under `control`'s rules (as the burn `Generator`).
    pub fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>> {
        let m = check_frame(&self.lay.spec, history, control)?;
        let rules = FrameRules::new(&self.lay.spec, &self.lay.slots, history, control)?;
        self.fit(m)?;
        let frame = self.frames;
        self.frames = self.frames.wrapping_add(1);
        let mut out = Vec::with_capacity(m);
        for g0 in (0..m).step_by(self.group) {
            let gs = self.group.min(m - g0);
            let forced = control.action.as_ref().map(|a| &a[g0..g0 + gs]);
            let started = std::time::Instant::now();
            let action = self.window_pass(&history[g0..g0 + gs], forced)?;
            self.prepare(&rules, control, g0, gs, action.as_deref(), frame)?;
            self.keep_logits(gs)?;
            if self.timed {
                self.x.sync()?;
            }
            let decoding = std::time::Instant::now();
            for p in 0..self.lay.n {
                let s = self.lay.seg_of[p];
                if !self.steps.contains_key(&(s, gs)) {
                    let ops = self.step_ops(s, gs)?;
                    self.steps.insert((s, gs), ops);
                }
                let key = (self.generation << 32) | ((s as u64) << 16) | gs as u64;
                match self.steps.get(&(s, gs)) {
                    Some(ops) => self.x.replay(key, ops)?,
                    None => return Err(GenerateError::Settings("a decoding step went missing".into())),
                }
            }
            let tok = self.x.read_i32(self.dec.tok, gs * self.lay.n)?;
            let counts = self.x.read_u32(self.dec.counts, 2)?;
            if self.timed {
                self.times.window += (decoding - started).as_secs_f64();
                self.times.decode += decoding.elapsed().as_secs_f64();
                self.times.steps += self.lay.n as u64;
            }
            self.new_agents.0 += u64::from(counts[0]);
            self.new_agents.1 += u64::from(counts[1]);
            for row in tok.chunks(self.lay.n) {
                out.push(row.iter().map(|&t| u32::try_from(t).unwrap_or(0)).collect());
            }
        }
        self.times.frames += u64::from(self.timed);
        Ok(out)
    }

    /// Waits for the device after each part of a frame and adds up the parts' times ([`Engine::times`]);
    /// the waits cost little (the host waits at the frame's end anyway) but end the host's run-ahead.
    pub fn timed(mut self, on: bool) -> Self {
        self.timed = on;
        self
    }

    /// Times every operation of the window pass (waiting for the device after each), by kind, from now on
    /// ([`Engine::window_profile`]).
    pub fn profiled(mut self, on: bool) -> Self {
        self.profile = on.then(Default::default);
        self
    }

    /// Seconds and counts of the window pass's operations by kind since profiling began.
    pub fn window_profile(&self) -> Vec<(String, f64, u64)> {
        self.profile
            .iter()
            .flatten()
            .map(|(k, (s, c))| (k.clone(), *s, *c))
            .collect()
    }

    /// Each operation of a decoding step of the largest vocabulary's segment for the last frame's group
    /// size, replayed `reps` times as one graph at the frame's middle position: microseconds per run, by
    /// operation, and whether it is one of the step's (the draw is also timed at top-k 1 and 64); after at
    /// least one frame, whose tables it reuses.
    pub fn profile_step(&mut self, reps: usize) -> Result<Vec<(String, f64, bool)>> {
        let s = (0..self.lay.spec.segments.len())
            .max_by_key(|&s| self.lay.spec.segments[s].vocab)
            .unwrap_or(0);
        let gs = self.steps.keys().map(|k| k.1).max().unwrap_or(1);
        let mut ops = self.step_ops(s, gs)?;
        let in_step = ops.len();
        // The draw again at top-k 1 and 64: what its rounds cost.
        if let Some(Op::Draw(d)) = ops.last().cloned() {
            for k in [1, 64] {
                ops.push(Op::Draw(umgen_cuda::ops::Draw {
                    top_k: k,
                    ..d.clone()
                }));
            }
        }
        let middle = (self.lay.n / 2) as i32;
        let mut out = Vec::with_capacity(ops.len());
        let mut layer = 0;
        for (i, op) in ops.iter().enumerate() {
            let batch = vec![op.clone(); reps.max(1)];
            let key = u64::MAX - i as u64;
            let mut best = f64::INFINITY;
            for _ in 0..3 {
                self.x
                    .write(self.dec.pos, umgen_cuda::ops::Data::I32(&[middle]))?;
                self.x.sync()?;
                let t0 = std::time::Instant::now();
                self.x.replay(key, &batch)?;
                self.x.sync()?;
                best = best.min(t0.elapsed().as_secs_f64());
            }
            let name = match op {
                Op::Gemv(g) => match g.output {
                    umgen_cuda::ops::GemvOut::Qkv { .. } => {
                        layer += 1;
                        format!("layer {layer}: ln1 + qkv")
                    }
                    _ => format!("gemv {} × {}", g.n, g.k),
                },
                Op::Draw(d) => format!("umgen_draw (top-k {})", d.top_k),
                other => other.name().to_string(),
            };
            out.push((name, 1e6 * best / reps.max(1) as f64, i < in_step));
        }
        self.x.forget_replays();
        self.steps.clear();
        Ok(out)
    }

    /// Runs an operation of the window pass (timed while profiling).
    fn run(&mut self, op: &Op) -> Result<()> {
        let Some(profile) = &self.profile else {
            return Ok(self.x.run(op)?);
        };
        let _ = profile;
        self.x.sync()?;
        let t0 = std::time::Instant::now();
        self.x.run(op)?;
        self.x.sync()?;
        let name = match op {
            Op::Gemm(g) => format!("gemm × {}", g.n),
            Op::AttendTiles(t) if t.causal.is_some() => "attend_tiles (time)".into(),
            Op::AttendTiles(_) => "attend_tiles (frame)".into(),
            other => other.name().into(),
        };
        if let Some(p) = &mut self.profile {
            let e = p.entry(name).or_insert((0.0, 0));
            e.0 += t0.elapsed().as_secs_f64();
            e.1 += 1;
        }
        Ok(())
    }

    /// The parts' times since the engine was made (zeros unless [`Engine::timed`]).
    pub fn times(&self) -> Times {
        self.times
    }

    /// New agents the new-agent rule tested so far, and how many it dropped.
    pub fn new_agents(&self) -> (u64, u64) {
        self.new_agents
    }

    /// Bytes of memory the executor's buffers hold.
    pub fn bytes(&self) -> usize {
        self.x.bytes()
    }

    /// The executor.
    pub fn executor(&self) -> &X {
        &self.x
    }

    /// Grows the working buffers to decode `m` scenes at a time (at most [`GEMV_ROWS`]).
    fn fit(&mut self, m: usize) -> Result<()> {
        let group = m.clamp(1, GEMV_ROWS);
        if group <= self.group {
            return Ok(());
        }
        let mut old = self.win.bufs();
        old.extend(self.dec.bufs());
        for b in old {
            self.x.free(b.id);
        }
        let chunk = (self.settings.pass_frames / self.settings.window).clamp(1, group);
        self.win = WindowBufs::new(&mut self.x, &self.lay, &self.sizes, chunk, self.settings.window)?;
        self.dec = DecodeBufs::new(&mut self.x, &self.lay, &self.sizes, group)?;
        (self.group, self.chunk) = (group, chunk);
        self.invalidate();
        Ok(())
    }

    /// Forgets the captured steps (after the step's buffers changed).
    fn invalidate(&mut self) {
        self.steps.clear();
        self.x.forget_replays();
        self.generation += 1;
    }
}
