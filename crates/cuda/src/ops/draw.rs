//! Arguments of the draw (`draw.cu`): a position's [`Rule`], the [`GroupRun`]s of token groups, [`Draw`].
//! Buffers, sizes and strides are in elements, as the kernel takes them (`src/kernels/*.cu` documents
//! each).

use super::Buf;

/// The largest top-k a draw takes as a list (`DRAW_KMAX` of `draw.cu`); larger ones (and 0) draw by
/// Gumbel-max over every id, which needs top-p 1.
pub const DRAW_KMAX: usize = 64;

/// Doubles a box takes in [`Draw::boxes`] (`BOX_WORDS` of `draw.cu`): x, y, heading, length, width; the
/// group's size if it is a new agent (negated once the rule empties it; 0 for the ego and old agents); the
/// group's first position.
pub const BOX_WORDS: usize = 7;

/// A position's rule for the draw (`Rule` of `draw.cu`, field for field).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rule {
    /// Prefilled: nothing to draw.
    pub known: i32,
    /// Drawn ids must be below it.
    pub limit: i32,
    /// The group's first position, or −1.
    pub gstart: i32,
    /// Index in the group.
    pub gj: i32,
    /// The group's run.
    pub grun: i32,
    /// The group's index among all groups.
    pub gindex: i32,
    /// Apply the new-agent rule here.
    pub finish: i32,
    /// Keep entry, or −1.
    pub keep: i32,
    /// The id a kept position redraws.
    pub keep_pad: i32,
    /// Its TAR logits' offset in a scene's keep row.
    pub keep_off: i32,
}

impl Rule {
    /// A position with nothing but its draw.
    pub const FREE: Self = Self {
        known: 0,
        limit: 1 << 30,
        gstart: -1,
        gj: 0,
        grun: 0,
        gindex: 0,
        finish: 0,
        keep: -1,
        keep_pad: 0,
        keep_off: 0,
    };
}

/// A run of token groups (`GroupRun` of `draw.cu`, field for field).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroupRun {
    /// Tokens per group.
    pub size: i32,
    /// Pad id.
    pub pad: i32,
    /// Values are below.
    pub values: i32,
    /// A group's last token is in `last_lo..last_hi`.
    pub last_lo: i32,
    /// End of that range.
    pub last_hi: i32,
    /// The new-agent rule: 0 none; 1 against the boxes decoded before the new agent (the official code's);
    /// 2 also against every old agent decoded after it (the whole frame).
    pub boxes: i32,
    /// Boxes a frame may hold.
    pub max_boxes: i32,
    /// x, y, heading, length, width: index in the group.
    pub field: [i32; 5],
    /// Their bins.
    pub bins: [i32; 5],
    /// Their lower ends.
    pub lo: [f64; 5],
    /// Their upper ends.
    pub hi: [f64; 5],
}

impl GroupRun {
    /// A run of no groups (the table's filler where a frame has none).
    pub const EMPTY: Self = Self {
        size: 0,
        pad: 0,
        values: 0,
        last_lo: 0,
        last_hi: 0,
        boxes: 0,
        max_boxes: 0,
        field: [0; 5],
        bins: [0; 5],
        lo: [0.0; 5],
        hi: [0.0; 5],
    };
}

/// The decoding step's draw for `m` scenes at the device position (see `draw.cu`).
#[derive(Debug, Clone)]
pub struct Draw {
    /// OAR logits `[m][vocab]`.
    pub logits: Buf,
    /// TAR logits of kept positions `[m][state[1]]`.
    pub keep_logits: Buf,
    /// Rules `[n]`.
    pub rules: Buf,
    /// Group runs.
    pub runs: Buf,
    /// Keep flags `[m][keeps]`.
    pub keep_on: Buf,
    /// Newborn flags `[m][groups]`.
    pub newborn: Buf,
    /// Tokens `[m][n]`.
    pub tok: Buf,
    /// The device position.
    pub pos: Buf,
    /// Blocks finished (u32).
    pub done: Buf,
    /// New agents tested and dropped (u32 × 2).
    pub counts: Buf,
    /// Boxes `[m][box_cap][BOX_WORDS]`.
    pub boxes: Buf,
    /// Boxes held `[m]`.
    pub nboxes: Buf,
    /// The frame's counter, the keep rows' scene stride and the first scene's index in the batch (u32 × 3).
    pub state: Buf,
    /// Temperature.
    pub temperature: f64,
    /// Top-p.
    pub top_p: f64,
    /// Top-p cuts only the ids after the most likely one, which keeps its probability
    /// (`umgen_generate::Sampling::top_p_rest`).
    pub top_p_rest: bool,
    /// Scenes.
    pub m: usize,
    /// Positions.
    pub n: usize,
    /// The segment's vocabulary.
    pub vocab: usize,
    /// Top-k (0: all).
    pub top_k: usize,
    /// Keep entries.
    pub keeps: usize,
    /// Groups.
    pub groups: usize,
    /// Box capacity per scene.
    pub box_cap: usize,
    /// The capacity of `keep_logits` per scene.
    pub keep_cap: usize,
    /// Runs in `runs`.
    pub run_count: usize,
    /// Philox key.
    pub key: [u32; 2],
}
