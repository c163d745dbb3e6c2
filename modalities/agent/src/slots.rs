//! Per-clip slot assignment: every track keeps one slot for the whole clip.

use std::collections::HashMap;
use umgen_modality::{ModalityError, Result};
use umgen_scene::SceneClip;

/// Which slot each kept track occupies in a clip.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SlotPlan {
    slots: HashMap<u64, usize>,
    dropped: usize,
}

#[derive(Debug, Clone, Copy)]
struct Track {
    id: u64,
    first_frame: usize,
    first_distance: f64,
    min_distance: f64,
}

impl SlotPlan {
    /// Slots for the tracks of `clip`. Tracks are ordered by first appearance (ties: nearer first, then
    /// lower id). With more than `max_slots` tracks, the `max_slots` tracks with the smallest distance to
    /// the ego over the clip are kept and then ordered the same way.
    pub fn new(clip: &SceneClip, max_slots: usize) -> Result<Self> {
        let mut tracks: Vec<Track> = Vec::new();
        let mut index: HashMap<u64, usize> = HashMap::new();
        for (t, frame) in clip.frames.iter().enumerate() {
            let mut seen = std::collections::HashSet::new();
            for a in &frame.agents {
                if !seen.insert(a.track_id) {
                    return Err(ModalityError::Tokenizer {
                        modality: "agent".into(),
                        message: format!("clip `{}` frame {t}: track {} appears twice", clip.id, a.track_id),
                    });
                }
                let d = a.distance();
                match index.get(&a.track_id) {
                    Some(&i) => tracks[i].min_distance = tracks[i].min_distance.min(d),
                    None => {
                        index.insert(a.track_id, tracks.len());
                        tracks.push(Track {
                            id: a.track_id,
                            first_frame: t,
                            first_distance: d,
                            min_distance: d,
                        });
                    }
                }
            }
        }
        let dropped = tracks.len().saturating_sub(max_slots);
        if dropped > 0 {
            tracks.sort_by(|a, b| {
                a.min_distance
                    .total_cmp(&b.min_distance)
                    .then(a.first_frame.cmp(&b.first_frame))
                    .then(a.id.cmp(&b.id))
            });
            tracks.truncate(max_slots);
        }
        tracks.sort_by(|a, b| {
            a.first_frame
                .cmp(&b.first_frame)
                .then(a.first_distance.total_cmp(&b.first_distance))
                .then(a.id.cmp(&b.id))
        });
        let slots = tracks.iter().enumerate().map(|(s, tr)| (tr.id, s)).collect();
        Ok(Self { slots, dropped })
    }

    /// The slot of a track, if it has one.
    pub fn slot(&self, track: u64) -> Option<usize> {
        self.slots.get(&track).copied()
    }

    /// Tracks given a slot.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Whether no track has a slot.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Tracks left without a slot.
    pub fn dropped(&self) -> usize {
        self.dropped
    }
}
