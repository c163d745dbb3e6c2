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
use rand::{SeedableRng, rngs::StdRng};
use std::collections::HashMap;
use umgen_backbone::{PlainBackbone, Slot};
use umgen_cuda::ops::{Buf, DRAW_KMAX, Elem, Exec, GEMV_ROWS, MAX_HEAD, Op};
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

/// The window pass's buffers, for `chunk` scenes of `window` frames.
#[derive(Debug)]
struct WindowBufs {
    tok: Buf,
    act: Buf,
    x: Buf,
    xn: Buf,
    qkv: Buf,
    att: Buf,
    hid: Buf,
    hid_rows: usize,
    fresh_tok: Buf,
    fresh: Buf,
    map: Option<Buf>,
    align_base: Option<Buf>,
    track: Option<(Buf, Buf, Buf)>,
    ego: Option<EgoBufs>,
}

/// The ego module's buffers.
#[derive(Debug)]
struct EgoBufs {
    eq: Buf,
    qn: Buf,
    qf: Buf,
    ctx: Buf,
    kv: Buf,
    y: Buf,
    hid: Buf,
    logits: Buf,
}

/// The decoding step's buffers, for `group` scenes.
#[derive(Debug)]
struct DecodeBufs {
    h: Buf,
    xs: Buf,
    t1: Buf,
    q: Buf,
    y: Buf,
    hb: Buf,
    logits: Buf,
    kc: Vec<Buf>,
    vc: Vec<Buf>,
    pos: Buf,
    done: Buf,
    counts: Buf,
    state: Buf,
    keep_idx: Buf,
    tok: Buf,
    rules: Buf,
    caps: Caps,
    tables: Option<Tables>,
}

/// Capacities of the per-frame tables a control sizes: group runs, keep entries, groups, keep logits per
/// scene. Growing one reallocates its table and forgets the captured steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Caps {
    runs: usize,
    keeps: usize,
    groups: usize,
    keep_logits: usize,
}

/// The per-frame tables of [`Caps`].
#[derive(Debug, Clone, Copy)]
struct Tables {
    runs: Buf,
    keep_on: Buf,
    newborn: Buf,
    boxes: Buf,
    nboxes: Buf,
    keep_logits: Buf,
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
        let w = Weights::upload(&mut x, model)?;
        let group = GEMV_ROWS;
        let chunk = (settings.pass_frames / settings.window).clamp(1, group);
        let win = WindowBufs::new(&mut x, &lay, model, chunk, settings.window)?;
        let dec = DecodeBufs::new(&mut x, &lay, model, group)?;
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
        })
    }

    /// The next frame `[m][N]` of each of `m` scenes from their histories `[m][t][N]` (all of one length;
    /// `t = 0` makes initial scenes without TAR), under `control`'s rules (as the burn `Generator`).
    pub fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>> {
        let m = check_frame(&self.lay.spec, history, control)?;
        let rules = FrameRules::new(&self.lay.spec, &self.lay.slots, history, control)?;
        let frame = self.frames;
        self.frames = self.frames.wrapping_add(1);
        let mut out = Vec::with_capacity(m);
        for g0 in (0..m).step_by(self.group) {
            let gs = self.group.min(m - g0);
            let forced = control.action.as_ref().map(|a| &a[g0..g0 + gs]);
            let action = self.window_pass(&history[g0..g0 + gs], forced)?;
            self.prepare(&rules, control, g0, gs, action.as_deref(), frame)?;
            self.keep_logits(gs)?;
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
            self.new_agents.0 += u64::from(counts[0]);
            self.new_agents.1 += u64::from(counts[1]);
            for row in tok.chunks(self.lay.n) {
                out.push(row.iter().map(|&t| u32::try_from(t).unwrap_or(0)).collect());
            }
        }
        Ok(out)
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

    /// Forgets the captured steps (after the step's buffers changed).
    fn invalidate(&mut self) {
        self.steps.clear();
        self.x.forget_replays();
        self.generation += 1;
    }
}

/// A new zeroed buffer.
fn alloc<X: Exec>(x: &mut X, elem: Elem, len: usize) -> Result<Buf> {
    Ok(x.alloc(elem, len)?)
}

impl WindowBufs {
    fn new<X: Exec>(x: &mut X, lay: &Layout, m: &PlainBackbone, chunk: usize, window: usize) -> Result<Self> {
        let (n, d) = (lay.n, lay.d);
        let frames = chunk * window;
        let rows = frames * n;
        let hid_rows = rows.min(HIDDEN_ROWS);
        let spec = &lay.spec;
        let block = spec
            .action
            .as_ref()
            .map_or(1, |a| spec.segments[a.segment].block_len);
        let map = match &spec.align {
            Some(al) => Some(alloc(x, Elem::F32, frames * al.rows * al.cols * d)?),
            None => None,
        };
        let align_base = match &spec.align {
            Some(al) => {
                let mut base = Vec::with_capacity(al.rows * al.cols * 2);
                for r in 0..al.rows {
                    for c in 0..al.cols {
                        base.push((2.0 * c as f32 + 1.0) / al.cols as f32 - 1.0);
                        base.push((2.0 * r as f32 + 1.0) / al.rows as f32 - 1.0);
                    }
                }
                Some(weights::upload(x, Elem::F32, &base)?)
            }
            None => None,
        };
        let track = match (&spec.track, &m.track) {
            (Some(t), Some(_)) => {
                let l = spec.segments[t.segment].tokens;
                Some((
                    alloc(x, Elem::I32, frames * l)?,
                    alloc(x, Elem::F32, frames * l * d)?,
                    alloc(x, Elem::F32, chunk * l * d)?,
                ))
            }
            _ => None,
        };
        let ego = match &m.ego {
            Some(g) => {
                let [_, len] = g.block;
                let ctx_rows = (window * len).max(n - len);
                let q = chunk * g.q;
                Some(EgoBufs {
                    eq: alloc(x, Elem::F32, q * d)?,
                    qn: alloc(x, Elem::W, q * d)?,
                    qf: alloc(x, Elem::F32, q * d)?,
                    ctx: alloc(x, Elem::W, chunk * ctx_rows * d)?,
                    kv: alloc(x, Elem::W, chunk * ctx_rows * 2 * d)?,
                    y: alloc(x, Elem::F32, q * d)?,
                    hid: alloc(x, Elem::W, q * lay.hidden.max(d))?,
                    logits: alloc(x, Elem::F32, q * g.head.d_out)?,
                })
            }
            None => None,
        };
        Ok(Self {
            tok: alloc(x, Elem::I32, rows)?,
            act: alloc(x, Elem::F32, frames * 3)?,
            x: alloc(x, Elem::F32, rows * d)?,
            xn: alloc(x, Elem::W, rows * d.max(lay.e))?,
            qkv: alloc(x, Elem::W, rows * 3 * d)?,
            att: alloc(x, Elem::W, rows * d)?,
            hid: alloc(x, Elem::W, hid_rows * lay.hidden.max(d))?,
            hid_rows,
            fresh_tok: alloc(x, Elem::I32, chunk * block)?,
            fresh: alloc(x, Elem::F32, chunk * block * d)?,
            map,
            align_base,
            track,
            ego,
        })
    }
}

impl DecodeBufs {
    fn new<X: Exec>(x: &mut X, lay: &Layout, m: &PlainBackbone, group: usize) -> Result<Self> {
        let (n, d) = (lay.n, lay.d);
        let vmax = lay.spec.segments.iter().map(|s| s.vocab).max().unwrap_or(1);
        let cache = group * lay.heads * n * lay.dh;
        let layers = m.oar.len();
        Ok(Self {
            h: alloc(x, Elem::F32, group * n * d)?,
            xs: alloc(x, Elem::F32, group * d)?,
            t1: alloc(x, Elem::F32, group * d)?,
            q: alloc(x, Elem::F32, group * d)?,
            y: alloc(x, Elem::F32, group * d)?,
            hb: alloc(x, Elem::F32, group * lay.hidden)?,
            logits: alloc(x, Elem::F32, group * vmax)?,
            kc: (0..layers)
                .map(|_| alloc(x, Elem::W, cache))
                .collect::<Result<_>>()?,
            vc: (0..layers)
                .map(|_| alloc(x, Elem::W, cache))
                .collect::<Result<_>>()?,
            pos: alloc(x, Elem::I32, 1)?,
            done: alloc(x, Elem::U32, 1)?,
            counts: alloc(x, Elem::U32, 2)?,
            state: alloc(x, Elem::U32, 3)?,
            keep_idx: alloc(x, Elem::I32, n)?,
            tok: alloc(x, Elem::I32, group * n)?,
            rules: alloc(x, Elem::Rule, n)?,
            caps: Caps {
                runs: 0,
                keeps: 0,
                groups: 0,
                keep_logits: 0,
            },
            tables: None,
        })
    }
}
