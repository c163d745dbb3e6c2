//! Arguments of the row kernels (`rows.cu`): norms, bias and GELU, embeddings, the action shift, AMA's
//! alignment and the tracked slots' move.
//! Buffers, sizes and strides are in elements, as the kernel takes them (`src/kernels/*.cu` documents
//! each).

use super::Buf;

/// `dst[r] (+)= gelu?(norm?(src[r']) + bias)`: row `r` is `(i1, i2) = (r / inner, r % inner)`, its source
/// `src + (i1 % period)·src_s1 + idx[i2]·src_s2` (period 0: none; no `idx`: `i2`), its destination `dst +
/// i1·dst_s1 + i2·dst_s2` (f32 or `W`; adding into f32 only).
#[derive(Debug, Clone)]
pub struct Rows {
    /// Source rows (f32).
    pub src: Buf,
    /// Source row indices (i32), or none.
    pub idx: Option<Buf>,
    /// Destination rows.
    pub dst: Buf,
    /// Layer norm scale and shift.
    pub norm: Option<(Buf, Buf)>,
    /// Bias.
    pub bias: Option<Buf>,
    /// Source outer stride.
    pub src_s1: usize,
    /// Source inner stride.
    pub src_s2: usize,
    /// Period of the outer index (0: none).
    pub period: usize,
    /// Destination outer stride.
    pub dst_s1: usize,
    /// Destination inner stride.
    pub dst_s2: usize,
    /// Rows.
    pub rows: usize,
    /// Inner count.
    pub inner: usize,
    /// Columns.
    pub d: usize,
    /// Add into the destination.
    pub add: bool,
    /// GELU.
    pub gelu: bool,
}

/// `x = gelu?(x + bias)` on `rows` rows of `cols` (`ld` apart) of a `W` buffer.
#[derive(Debug, Clone)]
pub struct BiasT {
    /// The rows.
    pub x: Buf,
    /// The bias.
    pub bias: Buf,
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Row stride.
    pub ld: usize,
    /// GELU.
    pub gelu: bool,
}

/// `out[r] = table[row_base[seg_of[p]] + tok[r]] + pos_emb[p]` with `p = p0 + r % period`, into `W` rows of `e`.
#[derive(Debug, Clone)]
pub struct Embed {
    /// Table rows of every segment.
    pub table: Buf,
    /// Each segment's first row.
    pub row_base: Buf,
    /// Each position's segment.
    pub seg_of: Buf,
    /// Tokens.
    pub tok: Buf,
    /// Position embeddings.
    pub pos_emb: Buf,
    /// Results.
    pub out: Buf,
    /// Rows.
    pub rows: usize,
    /// Positions cycle with this period…
    pub period: usize,
    /// … from this one.
    pub p0: usize,
    /// Width.
    pub e: usize,
}

/// The action block of each frame of `x` `[m][w][n][d]` replaced by the next frame's (the last by `fresh`
/// `[m][len][d]`).
#[derive(Debug, Clone)]
pub struct Shift {
    /// The window's features.
    pub x: Buf,
    /// The new frame's block.
    pub fresh: Buf,
    /// Scenes.
    pub m: usize,
    /// Frames.
    pub w: usize,
    /// Positions per frame.
    pub n: usize,
    /// Width.
    pub d: usize,
    /// The block's first position.
    pub start: usize,
    /// Its length.
    pub len: usize,
}

/// AMA: each frame's map cells of `x` `[frames][n][d]` (at `offset`) get the bilinear sample of `src`
/// (their copy) at the cell moved by the frame's next action `act` `[frames][3]`.
#[derive(Debug, Clone)]
pub struct Align {
    /// Features.
    pub x: Buf,
    /// The map cells' copy `[frames][rows·cols][d]`.
    pub src: Buf,
    /// Actions (dx, dy, dθ).
    pub act: Buf,
    /// Cell centres in normalised units `[rows·cols][2]`.
    pub base: Buf,
    /// Frames.
    pub frames: usize,
    /// Positions per frame.
    pub n: usize,
    /// Width.
    pub d: usize,
    /// The map's first position.
    pub offset: usize,
    /// Grid rows.
    pub rows: usize,
    /// Grid columns.
    pub cols: usize,
    /// −2 / (cols · cell size).
    pub tx_scale: f32,
    /// −2 / (rows · cell size).
    pub ty_scale: f32,
}

/// One field of a tracked slot: its place in the slot and its bins.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackField {
    /// Position in the slot.
    pub index: usize,
    /// Lower end.
    pub lo: f32,
    /// Upper end.
    pub hi: f32,
    /// Bins.
    pub bins: u32,
    /// Bin width, `(hi − lo) / bins` computed in f64.
    pub width: f32,
}

impl TrackField {
    /// The centre of bin `id`, in burn's f32 order: `(id + 0.5) · width + lo`.
    pub fn centre(&self, id: i32) -> f32 {
        (id as f32 + 0.5) * self.width + self.lo
    }
}

/// The tracked slots of each frame's tokens moved one frame ahead (`backbone::track::moved`).
#[derive(Debug, Clone)]
pub struct Track {
    /// The window's tokens `[frames][n]`.
    pub tok: Buf,
    /// Each frame's next action `[frames][3]`.
    pub act: Buf,
    /// Moved tokens `[frames][slots·k]`.
    pub out: Buf,
    /// Frames (scenes × window).
    pub frames: usize,
    /// Window frames per scene.
    pub w: usize,
    /// Positions per frame.
    pub n: usize,
    /// The segment's first content position.
    pub offset: usize,
    /// Slots.
    pub slots: usize,
    /// Tokens per slot.
    pub k: usize,
    /// Ids below are values.
    pub values: u32,
    /// The pad id that empties slots moved out of range.
    pub pad: Option<u32>,
    /// Constant acceleration.
    pub accel: bool,
    /// x, y, vx, vy, heading.
    pub fields: [TrackField; 5],
    /// Seconds per frame.
    pub step: f32,
    /// Braking for a slower slot ahead (`backbone::FollowSpec`), when on.
    pub follow: Option<TrackFollow>,
    /// Stop points the follow rule also brakes for (`backbone::StopSpec`), when on.
    pub stops: Option<TrackStops>,
}

/// Most state ids of [`TrackStops::stop`] and [`TrackStops::go`] (`backbone::STOP_IDS`).
pub const TRACK_STOP_IDS: usize = 4;

/// `backbone::StopSpec` as the `track` operation reads it: slots of another segment of the same frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackStops {
    /// The stop segment's first content position.
    pub offset: usize,
    /// Slots.
    pub slots: usize,
    /// Tokens per slot.
    pub k: usize,
    /// Ids below are values.
    pub values: u32,
    /// x, y and heading (`hi` unused).
    pub fields: [TrackField; 3],
    /// Position of the state token.
    pub state: usize,
    /// State ids that ask to stop; −1 fills unused entries.
    pub stop: [i32; TRACK_STOP_IDS],
    /// State ids that release the stops at their x and y ids; −1 fills unused entries.
    pub go: [i32; TRACK_STOP_IDS],
    /// Distance (m) before a point at which a follower's centre stands.
    pub gap: f32,
}

impl TrackStops {
    /// The points of frame `frame` of tokens `tok` `[frames][n]` that ask to stop, as the centres of
    /// their x, y and heading bins: slots whose x is a value, whose state is a stop id, and with no slot
    /// at the same x and y ids showing a go id.
    pub fn points(&self, tok: &[i32], n: usize, frame: usize) -> Vec<[f32; 3]> {
        let slot = |j: usize| {
            let at = frame * n + self.offset + j * self.k;
            &tok[at..at + self.k]
        };
        let (ix, iy) = (self.fields[0].index, self.fields[1].index);
        let has = |ids: &[i32; TRACK_STOP_IDS], id: i32| ids.iter().any(|&s| s >= 0 && s == id);
        let released = |o: &[i32]| {
            (0..self.slots).any(|g| {
                let p = slot(g);
                p[ix] == o[ix] && p[iy] == o[iy] && has(&self.go, p[self.state])
            })
        };
        (0..self.slots)
            .map(slot)
            .filter(|o| o[ix] < self.values as i32 && has(&self.stop, o[self.state]) && !released(o))
            .map(|o| std::array::from_fn(|q| self.fields[q].centre(o[self.fields[q].index])))
            .collect()
    }
}

/// `backbone::FollowSpec` in f32, as burn's scalars reach its f32 operations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackFollow {
    /// Most distance (m) of a leader's centre from the slot's axis.
    pub half_width: f32,
    /// Least cosine between the two headings.
    pub cos_heading: f32,
    /// Distance (m) between centres at which the speeds should match.
    pub min_gap: f32,
    /// Least room (m) divided by.
    pub min_room: f32,
    /// Least deceleration (m/s²) that changes the hint.
    pub onset: f32,
    /// Most deceleration (m/s²).
    pub max: f32,
}
