//! What the backbone needs to know about the frame: segments, vocabularies, codebooks, and which segments
//! carry the ego action and the alignable map. No modality names are interpreted here.

use crate::config::BackboneConfig;
use crate::error::{BackboneError, Result};
use serde::{Deserialize, Serialize};

/// One modality's block in the frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmentSpec {
    /// Label for logs and metric names.
    pub label: String,
    /// First position of the block (its start token when there are boundary tokens).
    pub block_start: usize,
    /// Positions of the block, boundary tokens included.
    pub block_len: usize,
    /// First content position.
    pub offset: usize,
    /// Content tokens.
    pub tokens: usize,
    /// Content ids `0..vocab` (the output vocabulary).
    pub vocab: usize,
    /// Embedding table rows (content, start and end ids).
    pub embed_vocab: usize,
    /// Content ids `0..ordinal` are ordered scalar bins (0: unordered codes); with
    /// `backbone.ordinal_init` their embedding and head rows start as a sinusoid of the bin index.
    #[serde(default)]
    pub ordinal: usize,
    /// A pre-trained codebook `[vocab, dim]` (row-major) that initialises the embedding table.
    #[serde(skip)]
    pub codebook: Option<(usize, Vec<f32>)>,
}

/// The ego action: a segment whose first three content tokens are dx, dy, dθ in uniform bins.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionSpec {
    /// Segment index.
    pub segment: usize,
    /// `(lo, hi, bins)` of dx (m), dy (m) and dθ (rad).
    pub bins: [(f64, f64, u32); 3],
}

impl ActionSpec {
    /// The value at the centre of bin `id` of component `k`.
    pub fn decode(&self, k: usize, id: u32) -> f64 {
        let (lo, hi, n) = self.bins[k];
        lo + (f64::from(id) + 0.5) * (hi - lo) / f64::from(n)
    }
}

/// The map that AMA moves: a metric bird's-eye grid (row 0 at the front, column 0 at the left).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignSpec {
    /// Segment index.
    pub segment: usize,
    /// Grid rows.
    pub rows: usize,
    /// Grid columns.
    pub cols: usize,
    /// Metres per cell.
    pub cell_m: f64,
}

/// Slots of tracked objects that the TAR sees moved one frame ahead (`backbone.track`, [`crate::track`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackSpec {
    /// Segment index.
    pub segment: usize,
    /// Tokens per slot.
    pub slot: usize,
    /// Ids `0..values` are value bins.
    pub values: u32,
    /// Position in the slot and `(lo, hi, bins)` of x, y (m), vx, vy (m/s) and the heading (rad).
    pub fields: [(usize, (f64, f64, u32)); 5],
    /// Seconds from one frame of a window to the next.
    pub step_s: f64,
    /// The segment's pad token: a slot moved past the x or y range is hinted as empty (every token
    /// pad), as the data leaves out agents outside the window. `None`: it keeps the end bins.
    #[serde(default)]
    pub pad: Option<u32>,
    /// Move by constant acceleration instead of constant velocity: the velocity's change since the
    /// window's previous frame is kept for one more frame (`backbone.track_accel`).
    #[serde(default)]
    pub accel: bool,
    /// Brake for a slower object ahead in the lane (`backbone.track_follow`); absent from manifests
    /// when off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub follow: Option<FollowSpec>,
    /// Stop points of another segment (a red light's stop line) that the follow rule brakes for as
    /// standing objects (`backbone.track_stops`); absent from manifests when off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stops: Option<StopSpec>,
}

/// Where the tracked slots stop (`backbone.track_stops`): slots of another segment, each a place, the
/// heading of the traffic that stops there and a state. A slot whose state is one of `stop`, with no
/// slot at the same place (the same x and y ids) in a `go` state, leads every tracked slot behind it
/// in its lane ([`FollowSpec`]'s test) as a standing object whose follower's centre stops `gap_m`
/// before it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StopSpec {
    /// Segment index.
    pub segment: usize,
    /// Tokens per slot.
    pub slot: usize,
    /// Ids `0..values` are value bins; a slot whose x is not one holds no point.
    pub values: u32,
    /// Position in the slot and `(lo, hi, bins)` of x, y (m) and the heading (rad).
    pub fields: [(usize, (f64, f64, u32)); 3],
    /// Position of the state token in the slot.
    pub state: usize,
    /// State ids that ask to stop.
    pub stop: Vec<u32>,
    /// State ids that release the stops at their place.
    pub go: Vec<u32>,
    /// Distance (m) before the point at which a follower's centre stands: half a car and half a
    /// metre.
    pub gap_m: f64,
}

impl StopSpec {
    /// A follower's centre stops this far (m) before a stop point: SUMO's cars are 5 m long and stand
    /// with their front about half a metre before the line.
    pub const GAP_M: f64 = 3.0;
}

/// Most state ids in a [`StopSpec`]'s `stop` and in its `go` (the generation kernels' fixed arrays).
pub const STOP_IDS: usize = 4;

/// When a tracked slot brakes for another ahead of it (`backbone.track_follow`). An object `j` leads
/// object `i` when `j`'s centre lies ahead along `i`'s heading, within `half_width_m` of its axis, and
/// `j` heads within `cos_heading` of `i`'s direction. Closing at `w` (m/s, `i`'s speed less `j`'s, both
/// along `i`'s heading) with `r` metres left before the gap between their centres is `min_gap_m`
/// (at least `min_room_m`), `i` needs `w² / (2r)` m/s² to match `j`'s speed in time; the hardest such
/// braking over its leaders, once it reaches `onset_m_s2`, replaces the slot's velocity change along
/// its heading where that is weaker, capped at `max_m_s2` and at a stop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FollowSpec {
    /// Most distance (m) of a leader's centre from the slot's axis: one lane.
    pub half_width_m: f64,
    /// Least cosine of the angle between the two headings: the same direction of travel.
    pub cos_heading: f64,
    /// Distance (m) between centres at which the slot should have the leader's speed: two half car
    /// lengths and a standing gap.
    pub min_gap_m: f64,
    /// Least room (m) the rule divides by, so that a leader closer than `min_gap_m` asks for the
    /// strongest braking rather than a division by nothing.
    pub min_room_m: f64,
    /// Least deceleration (m/s²) that changes the hint: below it the slot keeps its motion.
    pub onset_m_s2: f64,
    /// Most deceleration (m/s²) the hint applies.
    pub max_m_s2: f64,
}

impl Default for FollowSpec {
    /// SUMO-like cars: 5 m long with a standing gap of 2.5 m, lanes 3.2 m wide, emergency braking of
    /// 9 m/s²; braking from 1 m/s², twice the noise of 1,024 velocity bins over a 0.5 s step.
    fn default() -> Self {
        Self {
            half_width_m: 1.5,
            cos_heading: 30f64.to_radians().cos(),
            min_gap_m: 7.5,
            min_room_m: 0.5,
            onset_m_s2: 1.0,
            max_m_s2: 9.0,
        }
    }
}

impl TrackSpec {
    /// Whether frames `seconds` apart step as the model moves its slots (`step_s`, to a millionth).
    pub fn steps_by(&self, seconds: f64) -> bool {
        (seconds - self.step_s).abs() <= 1e-6 * self.step_s
    }
}

/// Everything the backbone is built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BackboneSpec {
    /// Positions per frame (N).
    pub n: usize,
    /// Blocks in frame order.
    pub segments: Vec<SegmentSpec>,
    /// The ego action, when the model predicts it.
    pub action: Option<ActionSpec>,
    /// The map AMA moves, when enabled.
    pub align: Option<AlignSpec>,
    /// The tracked objects moved by constant velocity and the ego motion, when enabled.
    #[serde(default)]
    pub track: Option<TrackSpec>,
}

impl BackboneSpec {
    /// Checks the spec against the config: contiguous blocks, valid segments, sizes that fit.
    pub fn validate(&self, cfg: &BackboneConfig) -> Result<()> {
        let fail = |m: String| Err(BackboneError::Spec(m));
        let mut pos = 0;
        for s in &self.segments {
            if s.block_start != pos
                || s.offset < s.block_start
                || s.offset + s.tokens > s.block_start + s.block_len
                || s.vocab == 0
                || s.embed_vocab < s.vocab
                || s.ordinal > s.vocab
            {
                return fail(format!(
                    "segment `{}` is not a contiguous block with a vocabulary",
                    s.label
                ));
            }
            if let Some((dim, data)) = &s.codebook
                && (*dim == 0 || data.len() != dim * s.vocab)
            {
                return fail(format!(
                    "segment `{}`: codebook of {} values is not {} × {dim}",
                    s.label,
                    data.len(),
                    s.vocab
                ));
            }
            pos += s.block_len;
        }
        if pos != self.n {
            return fail(format!(
                "segments cover {pos} positions, the frame has {}",
                self.n
            ));
        }
        if cfg.d_model == 0 || cfg.heads == 0 || !cfg.d_model.is_multiple_of(cfg.heads) {
            return fail(format!(
                "d_model {} must be a positive multiple of heads {}",
                cfg.d_model, cfg.heads
            ));
        }
        if let Some(a) = &self.action {
            let s = self.segments.get(a.segment).map(|s| s.tokens).unwrap_or(0);
            if s < 3 {
                return fail("the action segment needs dx, dy and dθ tokens".into());
            }
        }
        if let Some(a) = &self.align {
            let s = self.segments.get(a.segment).map(|s| s.tokens).unwrap_or(0);
            if s != a.rows * a.cols || a.cell_m.is_nan() || a.cell_m <= 0.0 {
                return fail("the align segment must be a metric grid".into());
            }
        }
        if let Some(k) = &self.track {
            let tokens = self.segments.get(k.segment).map(|s| s.tokens).unwrap_or(0);
            let fits = k.slot > 0
                && tokens > 0
                && tokens.is_multiple_of(k.slot)
                && k.fields
                    .iter()
                    .all(|(i, (lo, hi, n))| *i < k.slot && lo < hi && *n > 0 && *n <= k.values);
            if !fits || self.action.is_none() || !(k.step_s.is_finite() && k.step_s > 0.0) {
                return fail(format!(
                    "the tracked segment needs the ego action, slots of {} tokens that fill it, binned \
                     fields inside a slot and a positive frame step ({} s)",
                    k.slot, k.step_s
                ));
            }
        }
        if let Some(st) = self
            .track
            .as_ref()
            .and_then(|k| k.stops.as_ref().map(|st| (k, st)))
        {
            self.check_stops(st)?;
        }
        Ok(())
    }

    /// Checks the stop points of the tracked slots `k`.
    fn check_stops(&self, (k, st): (&TrackSpec, &StopSpec)) -> Result<()> {
        let (tokens, vocab) = self
            .segments
            .get(st.segment)
            .map_or((0, 0), |s| (s.tokens, s.vocab as u32));
        let fits = st.slot > 0
            && tokens > 0
            && tokens.is_multiple_of(st.slot)
            && st.state < st.slot
            && st
                .fields
                .iter()
                .all(|(i, (lo, hi, n))| *i < st.slot && lo < hi && *n > 0 && *n <= st.values);
        let ids = |v: &[u32], least: usize| {
            (least..=STOP_IDS).contains(&v.len()) && v.iter().all(|&id| id >= st.values && id < vocab)
        };
        let ok = fits && ids(&st.stop, 1) && ids(&st.go, 0) && st.gap_m.is_finite() && st.gap_m >= 0.0;
        if !ok {
            return Err(BackboneError::Spec(format!(
                "the stop segment needs slots of {} tokens that fill it, binned fields and a state inside a \
                 slot, 1 to {STOP_IDS} stop and up to {STOP_IDS} go state ids past the value bins, and a \
                 gap of at least 0 m ({} m)",
                st.slot, st.gap_m
            )));
        }
        if k.follow.is_none() || st.segment == k.segment {
            return Err(BackboneError::Spec(
                "stop points need the follow rule and a segment other than the tracked one".into(),
            ));
        }
        Ok(())
    }

    /// Floating-point operations of one training step on `batch` windows of `frames + 1` frames: the forward
    /// pass's matrix products and attention counted as 2 per multiply-add, times 3 for the backward pass.
    pub fn train_flops(&self, cfg: &BackboneConfig, batch: usize, frames: usize) -> f64 {
        let (d, e, r) = (cfg.d_model as f64, cfg.embed() as f64, cfg.mlp_ratio as f64);
        let (n, t) = (self.n as f64, frames as f64);
        // Per token of a pre-norm layer: projections (3 + 1) d², MLP 2 r d², attention 2 · ctx · d.
        let layer = |tokens: f64, ctx: f64| tokens * (2.0 * (4.0 * d * d + 2.0 * r * d * d) + 4.0 * ctx * d);
        let embed = (t + 1.0) * n * 2.0 * (e * d + d * d);
        let ego = match &self.action {
            Some(a) => {
                let s = &self.segments[a.segment];
                let (q, len) = (t * s.tokens as f64, s.block_len as f64);
                // Cross layers: queries through q, out and MLP; the context through k and v.
                let cross = |ctx_tokens: f64, ctx: f64| {
                    q * (2.0 * (2.0 * d * d + 2.0 * r * d * d) + 4.0 * ctx * d) + ctx_tokens * 4.0 * d * d
                };
                cfg.ego_hist_layers as f64 * cross(t * len, t * len)
                    + cfg.ego_env_layers as f64 * cross(t * (n - len), n - len)
            }
            None => 0.0,
        };
        // The moved slots: embedded like a frame's, then projected.
        let track = match &self.track {
            Some(k) => t * self.segments[k.segment].tokens as f64 * 2.0 * (e * d + 3.0 * d * d),
            None => 0.0,
        };
        let tar = cfg.tar_layers as f64 * (layer(t * n, t) + layer(t * n, n));
        let oar = cfg.oar_layers as f64 * layer(t * n, n);
        let heads: f64 = self
            .segments
            .iter()
            .map(|s| 2.0 * 2.0 * d * s.vocab as f64 * t * s.tokens as f64)
            .sum();
        3.0 * batch as f64 * (embed + track + ego + tar + oar + heads)
    }

    /// Parameters of a backbone of `cfg` on this spec (without building it).
    pub fn param_count(&self, cfg: &BackboneConfig) -> usize {
        let (d, e, h) = (cfg.d_model, cfg.embed(), cfg.mlp_ratio * cfg.d_model);
        let linear = |i: usize, o: usize, bias: bool| i * o + if bias { o } else { 0 };
        let ln = 2 * d;
        let mlp = linear(d, h, true) + linear(h, d, true);
        let self_block = 2 * ln + linear(d, 3 * d, true) + linear(d, d, true) + mlp;
        let cross_block = 3 * ln + linear(d, d, true) + linear(d, 2 * d, true) + linear(d, d, true) + mlp;
        let tables: usize = self
            .segments
            .iter()
            .map(|s| match &s.codebook {
                Some((dim, _)) => s.embed_vocab * dim + linear(*dim, e, true),
                None => s.embed_vocab * e,
            })
            .sum();
        let embed = tables + self.n * e + linear(e, d, true) + linear(d, d, true);
        let heads: usize = 2 * self.segments.iter().map(|s| d * s.vocab).sum::<usize>();
        let ego = match &self.action {
            Some(a) => {
                let q = self.segments[a.segment].tokens;
                q * d
                    + (cfg.ego_hist_layers + cfg.ego_env_layers) * cross_block
                    + ln
                    + d * self.segments[a.segment].vocab
            }
            None => 0,
        };
        let track = if self.track.is_some() {
            2 * linear(d, d, true)
        } else {
            0
        };
        embed
            + track
            + cfg.max_frames * d
            + ego
            + cfg.tar_layers * 2 * self_block
            + ln
            + d
            + cfg.oar_layers * self_block
            + ln
            + heads
    }
}
