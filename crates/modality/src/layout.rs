//! The frame layout: where each modality's tokens sit in a frame, derived from the registry.

use crate::error::{ModalityError, Result};
use crate::spec::{Grid, ModalitySpec};
use serde::Serialize;
use sha2::{Digest, Sha256};

/// Where one modality's block sits in a frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Segment {
    /// Modality name.
    pub modality: String,
    /// Modality kind.
    pub kind: String,
    /// First position of the block (its start token, when boundary tokens are on).
    pub block_start: usize,
    /// Position of the start token.
    pub start_pos: Option<usize>,
    /// First content position.
    pub offset: usize,
    /// Content tokens.
    pub tokens: usize,
    /// Position of the end token.
    pub end_pos: Option<usize>,
    /// One past the block's last position.
    pub block_end: usize,
    /// Content ids are `0..vocab_size`.
    pub vocab_size: u32,
    /// Embedding table size (content, start and end ids).
    pub embed_vocab: u32,
    /// Start token id.
    pub start_id: u32,
    /// End token id.
    pub end_id: u32,
    /// Pad id, when the modality has one.
    pub pad_id: Option<u32>,
    /// Spatial grid of the content tokens.
    pub grid: Option<Grid>,
    /// Bins of the leading content tokens, when they are discretised scalars.
    pub bins: Vec<crate::scalar::ScalarBins>,
    /// The slot layout of tracked objects. Not part of the fingerprint: the modality's settings, which
    /// are, fix it, and token stores written before it existed stay valid.
    #[serde(skip)]
    pub tracks: Option<crate::spec::Tracks>,
    /// The slot layout of stop points, not part of the fingerprint for the same reason.
    #[serde(skip)]
    pub stops: Option<crate::stops::Stops>,
}

impl Segment {
    /// Content positions, as a range of frame positions.
    pub fn content(&self) -> std::ops::Range<usize> {
        self.offset..self.offset + self.tokens
    }
}

/// What a frame position holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// The block's start token.
    Start,
    /// Content token `i` of the block.
    Content(usize),
    /// The block's end token.
    End,
}

/// A frame position: its segment (index into [`FrameLayout::segments`]) and slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Position {
    /// Segment index.
    pub segment: usize,
    /// Slot within the segment.
    pub slot: Slot,
}

/// The token layout of one frame: modality blocks in registry order, each optionally wrapped by its own
/// start and end tokens. Ids are per modality: position `p` takes ids from its own modality's vocabulary.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameLayout {
    segments: Vec<Segment>,
    positions: Vec<Position>,
    boundary_tokens: bool,
    fingerprint: String,
}

impl FrameLayout {
    /// The layout of modalities in this order. `settings` are the modalities' tokenizer settings
    /// (one per spec), hashed into the fingerprint.
    pub fn new(specs: &[(&ModalitySpec, serde_json::Value)], boundary_tokens: bool) -> Result<Self> {
        if specs.is_empty() {
            return Err(ModalityError::Empty);
        }
        let mut segments = Vec::with_capacity(specs.len());
        let mut positions = Vec::new();
        for (index, (spec, _)) in specs.iter().enumerate() {
            spec.validate()?;
            if segments.iter().any(|s: &Segment| s.modality == spec.name) {
                return Err(ModalityError::DuplicateName {
                    name: spec.name.clone(),
                });
            }
            let block_start = positions.len();
            let start_pos = boundary_tokens.then_some(block_start);
            if boundary_tokens {
                positions.push(Position {
                    segment: index,
                    slot: Slot::Start,
                });
            }
            let offset = positions.len();
            positions.extend((0..spec.tokens_per_frame).map(|i| Position {
                segment: index,
                slot: Slot::Content(i),
            }));
            let end_pos = boundary_tokens.then_some(positions.len());
            if boundary_tokens {
                positions.push(Position {
                    segment: index,
                    slot: Slot::End,
                });
            }
            segments.push(Segment {
                modality: spec.name.clone(),
                kind: spec.kind.clone(),
                block_start,
                start_pos,
                offset,
                tokens: spec.tokens_per_frame,
                end_pos,
                block_end: positions.len(),
                vocab_size: spec.vocab_size,
                embed_vocab: spec.embed_vocab(),
                start_id: spec.start_id,
                end_id: spec.end_id,
                pad_id: spec.pad_id,
                grid: spec.grid,
                bins: spec.bins.clone(),
                tracks: spec.tracks,
                stops: spec.stops.clone(),
            });
        }
        let fingerprint = fingerprint(&segments, specs, boundary_tokens);
        Ok(Self {
            segments,
            positions,
            boundary_tokens,
            fingerprint,
        })
    }

    /// Positions per frame (N).
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Always false: a layout has at least one modality.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Whether every block is wrapped by start and end tokens.
    pub fn boundary_tokens(&self) -> bool {
        self.boundary_tokens
    }

    /// Segments in frame order.
    pub fn segments(&self) -> &[Segment] {
        &self.segments
    }

    /// The segment of a modality.
    pub fn segment(&self, modality: &str) -> Option<&Segment> {
        self.segments.iter().find(|s| s.modality == modality)
    }

    /// What position `p` holds.
    pub fn position(&self, p: usize) -> Option<Position> {
        self.positions.get(p).copied()
    }

    /// Every position in order.
    pub fn positions(&self) -> &[Position] {
        &self.positions
    }

    /// The ids allowed at position `p`, as a half-open range.
    pub fn allowed_ids(&self, p: usize) -> Option<std::ops::Range<u32>> {
        let pos = self.position(p)?;
        let s = &self.segments[pos.segment];
        Some(match pos.slot {
            Slot::Start => s.start_id..s.start_id + 1,
            Slot::Content(_) => 0..s.vocab_size,
            Slot::End => s.end_id..s.end_id + 1,
        })
    }

    /// Stable hash (hex SHA-256) of the layout, vocabularies, special ids and tokenizer settings.
    pub fn fingerprint(&self) -> &str {
        &self.fingerprint
    }

    /// One frame's row of N ids from per-modality content blocks (in segment order).
    pub fn assemble(&self, blocks: &[Vec<u32>]) -> Result<Vec<u32>> {
        if blocks.len() != self.segments.len() {
            return Err(ModalityError::Tokenizer {
                modality: "layout".into(),
                message: format!("{} blocks for {} modalities", blocks.len(), self.segments.len()),
            });
        }
        let mut row = Vec::with_capacity(self.len());
        for (s, block) in self.segments.iter().zip(blocks) {
            check_block(s, block)?;
            if self.boundary_tokens {
                row.push(s.start_id);
            }
            row.extend_from_slice(block);
            if self.boundary_tokens {
                row.push(s.end_id);
            }
        }
        Ok(row)
    }

    /// Per-modality content blocks of a frame row, after checking every id against its position.
    pub fn split<'a>(&self, row: &'a [u32]) -> Result<Vec<&'a [u32]>> {
        self.check_row(row)?;
        Ok(self.segments.iter().map(|s| &row[s.content()]).collect())
    }

    /// Checks a frame row: length N and every id allowed at its position.
    pub fn check_row(&self, row: &[u32]) -> Result<()> {
        if row.len() != self.len() {
            return Err(ModalityError::TokenCount {
                modality: "frame".into(),
                expected: self.len(),
                actual: row.len(),
            });
        }
        for (p, &id) in row.iter().enumerate() {
            let allowed = self.allowed_ids(p).unwrap_or(0..0);
            if !allowed.contains(&id) {
                let s = &self.segments[self.positions[p].segment];
                return Err(ModalityError::TokenOutOfVocab {
                    modality: s.modality.clone(),
                    position: p,
                    id,
                    allowed: format!("{}..{}", allowed.start, allowed.end),
                });
            }
        }
        Ok(())
    }
}

/// Checks one modality's content block against its segment.
pub(crate) fn check_block(s: &Segment, block: &[u32]) -> Result<()> {
    if block.len() != s.tokens {
        return Err(ModalityError::TokenCount {
            modality: s.modality.clone(),
            expected: s.tokens,
            actual: block.len(),
        });
    }
    if let Some((i, &id)) = block.iter().enumerate().find(|(_, id)| **id >= s.vocab_size) {
        return Err(ModalityError::TokenOutOfVocab {
            modality: s.modality.clone(),
            position: s.offset + i,
            id,
            allowed: format!("0..{}", s.vocab_size),
        });
    }
    Ok(())
}

fn fingerprint(segments: &[Segment], specs: &[(&ModalitySpec, serde_json::Value)], boundary: bool) -> String {
    // serde_json objects are BTreeMaps, so the text is canonical for equal inputs.
    let canonical = serde_json::json!({
        "format": 1,
        "boundary_tokens": boundary,
        "segments": segments,
        "settings": specs.iter().map(|(s, v)| serde_json::json!({"modality": s.name, "settings": v})).collect::<Vec<_>>(),
    });
    let digest = Sha256::digest(canonical.to_string().as_bytes());
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn specs() -> Vec<ModalitySpec> {
        vec![
            ModalitySpec::new("ego", "ego", 1024, 3),
            ModalitySpec::new("map", "map", 8192, 4).with_grid(2, 2),
            ModalitySpec::new("agent", "agent", 1028, 22).with_pad(1027),
        ]
    }

    fn layout(specs: &[ModalitySpec], boundary: bool) -> FrameLayout {
        let with: Vec<_> = specs.iter().map(|s| (s, serde_json::Value::Null)).collect();
        FrameLayout::new(&with, boundary).unwrap()
    }

    #[test]
    fn offsets_with_and_without_boundary_tokens() {
        let l = layout(&specs(), true);
        assert_eq!(l.len(), 5 + 6 + 24);
        let (ego, map, agent) = (&l.segments()[0], &l.segments()[1], &l.segments()[2]);
        assert_eq!(
            (ego.start_pos, ego.offset, ego.end_pos, ego.block_end),
            (Some(0), 1, Some(4), 5)
        );
        assert_eq!((map.block_start, map.offset, map.end_pos), (5, 6, Some(10)));
        assert_eq!((agent.offset, agent.block_end), (12, 35));
        assert_eq!(
            l.position(0),
            Some(Position {
                segment: 0,
                slot: Slot::Start
            })
        );
        assert_eq!(
            l.position(7),
            Some(Position {
                segment: 1,
                slot: Slot::Content(1)
            })
        );
        assert_eq!(l.allowed_ids(10), Some(8193..8194));
        assert_eq!(l.allowed_ids(12), Some(0..1028));
        let bare = layout(&specs(), false);
        assert_eq!(bare.len(), 29);
        assert_eq!(bare.segments()[2].offset, 7);
        assert_ne!(bare.fingerprint(), l.fingerprint());
    }

    #[test]
    fn fingerprint_is_stable_and_sensitive() {
        let a = layout(&specs(), true);
        assert_eq!(a.fingerprint(), layout(&specs(), true).fingerprint());
        assert_eq!(a.fingerprint().len(), 64);
        let mut changed = specs();
        changed[2] = ModalitySpec::new("agent", "agent", 1029, 22).with_pad(1027);
        assert_ne!(a.fingerprint(), layout(&changed, true).fingerprint());
        let s = specs();
        let with: Vec<_> = s.iter().map(|s| (s, serde_json::json!({"bins": 512}))).collect();
        assert_ne!(
            a.fingerprint(),
            FrameLayout::new(&with, true).unwrap().fingerprint()
        );
    }

    #[test]
    fn assemble_and_split_round_trip() {
        let l = layout(&specs(), true);
        let blocks = vec![
            vec![1, 2, 3],
            vec![8191, 0, 5, 6],
            (0..22).map(|i| 1000 + i).collect::<Vec<u32>>(),
        ];
        let row = l.assemble(&blocks).unwrap();
        assert_eq!(row.len(), l.len());
        assert_eq!(&row[..5], &[1024, 1, 2, 3, 1025]);
        let back = l.split(&row).unwrap();
        assert_eq!(back.iter().map(|b| b.to_vec()).collect::<Vec<_>>(), blocks);
    }

    #[test]
    fn bad_rows_and_blocks_are_named() {
        let l = layout(&specs(), true);
        let err = l
            .assemble(&[vec![1, 2], vec![0; 4], vec![0; 22]])
            .unwrap_err()
            .to_string();
        assert!(err.contains("`ego`") && err.contains("expected 3"), "{err}");
        let err = l
            .assemble(&[vec![1, 2, 1024], vec![0; 4], vec![0; 22]])
            .unwrap_err()
            .to_string();
        assert!(err.contains("`ego`") && err.contains("1024"), "{err}");
        let mut row = l.assemble(&[vec![0; 3], vec![0; 4], vec![0; 22]]).unwrap();
        row[5] = 7; // the map start token
        let err = l.check_row(&row).unwrap_err().to_string();
        assert!(
            err.contains("`map`") && err.contains("position 5") && err.contains("8192..8193"),
            "{err}"
        );
        let dup = [
            ModalitySpec::new("ego", "ego", 10, 1),
            ModalitySpec::new("ego", "x", 10, 1),
        ];
        let with: Vec<_> = dup.iter().map(|s| (s, serde_json::Value::Null)).collect();
        assert!(matches!(
            FrameLayout::new(&with, true),
            Err(ModalityError::DuplicateName { .. })
        ));
        assert!(matches!(FrameLayout::new(&[], true), Err(ModalityError::Empty)));
    }
}
