//! What the caller imposes on a frame ([`FrameControl`]) and the rules of its decoding that follow: what
//! may be drawn at each position (limits, token groups, keep redraws). Both decoders (the burn one in
//! `rollout.rs` and the engine's, which runs them on the device) read them from [`FrameRules`].

use crate::error::{GenerateError, Result};
use umgen_backbone::{BackboneSpec, Slot};

/// What the caller imposes on one new frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameControl {
    /// Action tokens (dx, dy, dθ ids) per scene of the batch, replacing the ego module's prediction.
    pub action: Option<Vec<Vec<u32>>>,
    /// Content tokens placed instead of drawn: frame position and the id for every scene. The OAR reads
    /// them like drawn ones, so the tokens after them react.
    pub tokens: Vec<(usize, u32)>,
    /// Positions whose drawn id must be below a limit (e.g. the value bins of a controlled agent slot,
    /// so that its other attributes are values, not pad or category ids).
    pub below: Vec<(usize, u32)>,
    /// Positions `(p, pad id, per scene)` where, for the scenes marked true, a drawn pad id is replaced by a
    /// draw from the TAR head with pad excluded: an agent present in the previous frame does not vanish
    /// on one OAR draw; the TAR, which sees the history, decides (the official code's heuristic).
    pub keep: Vec<(usize, u32, Vec<bool>)>,
    /// Runs of token groups that must each come out whole (agent slots: all pad, or values then a
    /// category).
    pub groups: Vec<TokenGroups>,
    /// Whole segments given for each scene (a modality as each context clip recorded it), placed
    /// instead of drawn: the tokens after them react, as to [`FrameControl::tokens`].
    pub given: Vec<GivenSegment>,
}

/// The content tokens of one segment for every scene of the batch.
#[derive(Debug, Clone, PartialEq)]
pub struct GivenSegment {
    /// The segment, by its index in the layout.
    pub segment: usize,
    /// Per scene, the segment's content ids in order.
    pub ids: Vec<Vec<u32>>,
}

/// `count` groups of `size` tokens from position `first`. A group's first token is a value or pad; after a
/// pad the rest is pad; otherwise the middle tokens are values and the last one is from `last`.
#[derive(Debug, Clone, PartialEq)]
pub struct TokenGroups {
    /// First position of the first group.
    pub first: usize,
    /// Tokens per group.
    pub size: usize,
    /// Groups.
    pub count: usize,
    /// The pad id.
    pub pad: u32,
    /// Value ids are `0..values`.
    pub values: u32,
    /// Ids of a group's last token (e.g. the categories).
    pub last: std::ops::Range<u32>,
    /// How to read a box from a group, for the new-agent rule (`None`: no rule).
    pub boxes: Option<crate::boxes::GroupBoxes>,
}

/// Per-position rules of one frame's decoding.
pub(crate) struct Rules<'a> {
    /// Per position: the id placed by the caller, for every scene.
    pub(crate) placed: &'a [Option<u32>],
    /// Per position: the ids given by the caller, one per scene.
    pub(crate) given: &'a [Option<Vec<u32>>],
    /// Per position: drawn ids must be below this.
    pub(crate) limits: &'a [Option<usize>],
    /// Per position: the pad id a kept agent redraws, and which scenes keep.
    pub(crate) keep: &'a [Option<(u32, Vec<bool>)>],
    /// Per position: the group's first position, the index in the group, the run in `groups`.
    pub(crate) group: &'a [Option<(usize, usize, usize)>],
    /// The caller's group runs.
    pub(crate) groups: &'a [TokenGroups],
    /// Per scene and position: the position's group was empty in the newest frame.
    pub(crate) newborn: &'a [Vec<bool>],
}

impl Rules<'_> {
    /// Whether position `p` may be drawn from its logits alone: no limit, no group, no keep rule (the
    /// host never reads such a position while the frame is decoded).
    pub(crate) fn free(&self, p: usize) -> bool {
        self.limits[p].is_none() && self.group[p].is_none() && self.keep[p].is_none()
    }

    /// Whether the caller set position `p` (for every scene, or one id per scene): nothing is drawn there,
    /// and a group holding it is the caller's (the new-agent rule never drops it).
    pub(crate) fn set_by_caller(&self, p: usize) -> bool {
        self.placed[p].is_some() || self.given[p].is_some()
    }
}

/// What may be drawn at a position.
pub(crate) enum Allowed {
    /// Nothing to draw: this id.
    Only(u32),
    /// Any id passing the test.
    Ids(Box<dyn Fn(u32) -> bool>),
}

/// The ids allowed at `p` of a scene whose frame so far is `row` (with `limited`, also below the position's
/// limit; the TAR redraw of a kept agent ignores limits, which only shape OAR draws).
pub(crate) fn allowed(rules: &Rules<'_>, p: usize, row: &[u32], limited: bool) -> Allowed {
    let limit = match (limited, rules.limits[p]) {
        (true, Some(k)) => k as u32,
        _ => u32::MAX,
    };
    match &rules.group[p] {
        None => Allowed::Ids(Box::new(move |id| id < limit)),
        Some((start, j, gi)) => {
            let g = &rules.groups[*gi];
            let (pad, values, last) = (g.pad, g.values, g.last.clone());
            if *j == 0 {
                Allowed::Ids(Box::new(move |id| id < limit && (id < values || id == pad)))
            } else if row[*start] == pad {
                Allowed::Only(pad)
            } else if *j + 1 == g.size {
                Allowed::Ids(Box::new(move |id| last.contains(&id)))
            } else {
                Allowed::Ids(Box::new(move |id| id < values && id < limit))
            }
        }
    }
}

/// Checks a batch of histories `[m][t][N]` (all of one length) and the control's forced action against the
/// spec; the number of scenes.
pub(crate) fn check_frame(
    spec: &BackboneSpec,
    history: &[Vec<Vec<u32>>],
    control: &FrameControl,
) -> Result<usize> {
    let m = history.len();
    let n = spec.n;
    let t = history.first().map_or(0, Vec::len);
    if m == 0
        || history
            .iter()
            .any(|h| h.len() != t || h.iter().any(|f| f.len() != n))
    {
        return Err(GenerateError::History(format!(
            "{m} scenes: each needs the same number of frames of {n} tokens"
        )));
    }
    let q = spec
        .action
        .as_ref()
        .map_or(0, |a| spec.segments[a.segment].tokens);
    if let Some(a) = &control.action
        && (a.len() != m || a.iter().any(|x| x.len() != q))
    {
        return Err(GenerateError::Settings(format!(
            "a forced action needs {q} tokens for each of the {m} scenes"
        )));
    }
    Ok(m)
}

/// One frame's rules, per position (and per scene where they differ), from a [`FrameControl`].
pub(crate) struct FrameRules {
    /// Per position: the id placed by the caller.
    pub(crate) placed: Vec<Option<u32>>,
    /// Per position: the ids given by the caller, one per scene.
    pub(crate) given: Vec<Option<Vec<u32>>>,
    /// Per position: drawn ids must be below this.
    pub(crate) limits: Vec<Option<usize>>,
    /// Per position: the pad id a kept agent redraws, and which scenes keep.
    pub(crate) keep: Vec<Option<(u32, Vec<bool>)>>,
    /// Per position: the group's first position, the index in the group, the run.
    pub(crate) group: Vec<Option<(usize, usize, usize)>>,
    /// Per scene and position: the position's group was empty in the newest frame.
    pub(crate) newborn: Vec<Vec<bool>>,
}

impl FrameRules {
    /// The rules `control` sets for the next frame of `history` (checked by [`check_frame`]); refuses
    /// placed tokens, limits, keep entries and groups that do not fit the frame.
    pub(crate) fn new(
        spec: &BackboneSpec,
        slots: &[Slot],
        history: &[Vec<Vec<u32>>],
        control: &FrameControl,
    ) -> Result<Self> {
        let (m, n) = (history.len(), spec.n);
        let mut placed = vec![None; n];
        for &(p, id) in &control.tokens {
            match slots.get(p) {
                Some(Slot::Content(s, _)) if (id as usize) < spec.segments[*s].vocab => placed[p] = Some(id),
                _ => {
                    return Err(GenerateError::Settings(format!(
                        "forced token {id} at position {p}: not a content position of this layout, or outside its vocabulary"
                    )));
                }
            }
        }
        let given = given_ids(spec, slots, m, control, &placed)?;
        let mut limits = vec![None; n];
        for &(p, lim) in &control.below {
            if p >= n || lim == 0 {
                return Err(GenerateError::Settings(format!(
                    "id limit {lim} at position {p}: outside the frame or empty"
                )));
            }
            limits[p] = Some(lim as usize);
        }
        let mut keep = vec![None; n];
        for (p, pad, scenes) in &control.keep {
            if *p >= n || scenes.len() != m {
                return Err(GenerateError::Settings(format!(
                    "keep at position {p}: outside the frame, or not one flag per scene"
                )));
            }
            keep[*p] = Some((*pad, scenes.clone()));
        }
        let mut group = vec![None; n];
        for (gi, g) in control.groups.iter().enumerate() {
            if g.size < 2 || g.first + g.size * g.count > n {
                return Err(GenerateError::Settings(format!(
                    "token groups from {} ({} × {}): outside the frame or smaller than 2",
                    g.first, g.count, g.size
                )));
            }
            for k in 0..g.count * g.size {
                group[g.first + k] = Some((g.first + (k / g.size) * g.size, k % g.size, gi));
            }
        }
        // Groups empty in each scene's newest frame (all of them for an initial scene).
        let newborn = history
            .iter()
            .map(|h| {
                (0..n)
                    .map(|p| match (&group[p], h.last()) {
                        (Some((start, _, gi)), Some(f)) => f.get(*start) == Some(&control.groups[*gi].pad),
                        (Some(_), None) => true,
                        _ => false,
                    })
                    .collect()
            })
            .collect();
        Ok(Self {
            placed,
            given,
            limits,
            keep,
            group,
            newborn,
        })
    }

    /// The rules as the decoders read them.
    pub(crate) fn view<'a>(&'a self, groups: &'a [TokenGroups]) -> Rules<'a> {
        Rules {
            newborn: &self.newborn,
            placed: &self.placed,
            given: &self.given,
            limits: &self.limits,
            keep: &self.keep,
            group: &self.group,
            groups,
        }
    }
}

/// Per position, the ids `control.given` sets for each of the `m` scenes; refuses an unknown or repeated
/// segment, the ego action's segment (given as [`FrameControl::action`], which also replaces the ego
/// module's prediction), a wrong number of scenes or tokens, ids outside the vocabulary, and positions
/// that `control.tokens` also places.
fn given_ids(
    spec: &BackboneSpec,
    slots: &[Slot],
    m: usize,
    control: &FrameControl,
    placed: &[Option<u32>],
) -> Result<Vec<Option<Vec<u32>>>> {
    let mut given: Vec<Option<Vec<u32>>> = vec![None; slots.len()];
    for (k, g) in control.given.iter().enumerate() {
        let bad = |why: String| GenerateError::Settings(format!("given segment {}: {why}", g.segment));
        let seg = spec
            .segments
            .get(g.segment)
            .ok_or_else(|| bad(format!("this layout has {} segments", spec.segments.len())))?;
        let label = &seg.label;
        if control.given[..k].iter().any(|o| o.segment == g.segment) {
            return Err(bad(format!("`{label}` is given twice")));
        }
        if spec.action.as_ref().is_some_and(|a| a.segment == g.segment) {
            return Err(bad(format!(
                "`{label}` is the ego action: give it as the frame's action, which also replaces the ego module's prediction"
            )));
        }
        if g.ids.len() != m {
            return Err(bad(format!(
                "`{label}` given for {} scenes, the batch has {m}",
                g.ids.len()
            )));
        }
        if let Some((b, row)) = g.ids.iter().enumerate().find(|(_, r)| r.len() != seg.tokens) {
            return Err(bad(format!(
                "`{label}` of scene {b} has {} tokens, the segment {}",
                row.len(),
                seg.tokens
            )));
        }
        if let Some((b, id)) = g
            .ids
            .iter()
            .enumerate()
            .find_map(|(b, r)| r.iter().find(|&&id| id as usize >= seg.vocab).map(|&id| (b, id)))
        {
            return Err(bad(format!(
                "`{label}` of scene {b} holds id {id}, outside its {} ids",
                seg.vocab
            )));
        }
        for (p, slot) in slots.iter().enumerate() {
            if let Slot::Content(s, i) = *slot
                && s == g.segment
            {
                if placed[p].is_some() {
                    return Err(bad(format!(
                        "`{label}` is given, and a token is also placed at its position {p}"
                    )));
                }
                given[p] = Some(g.ids.iter().map(|r| r[i]).collect());
            }
        }
    }
    Ok(given)
}
