//! The rules of one frame's decoding: what may be drawn at each position (limits, token groups, keep
//! redraws), from the caller's [`FrameControl`](crate::FrameControl).

use crate::rollout::TokenGroups;

/// Per-position rules of one frame's decoding.
pub(crate) struct Rules<'a> {
    /// Per position: the id placed by the caller, for every scene.
    pub(crate) placed: &'a [Option<u32>],
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
