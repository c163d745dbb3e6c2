//! What a modality declares about its tokens.

use crate::error::{ModalityError, Result};
use serde::{Deserialize, Serialize};

/// Rows × columns of a modality whose tokens form a spatial grid (row-major), used by map alignment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Metres covered by one cell, when the grid is a metric bird's-eye view (row 0 at the front, column
    /// 0 at the left), so that it can be moved by an ego motion.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell_m: Option<f64>,
}

/// Slots of tracked objects (the agents): fixed-size groups of tokens, each an object's state in the
/// frame's ego coordinates, so that a model can move a slot to where constant velocity and the ego's own
/// motion put it one frame later (`backbone.track`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tracks {
    /// Tokens per slot.
    pub slot: usize,
    /// Ids `0..values` are value bins; a slot whose `x` token is not one (a pad, say) is not moved.
    pub values: u32,
    /// Position in the slot and bins of `x`, `y` (m), `vx`, `vy` (m/s) and the heading (rad), in that
    /// order.
    pub fields: [(usize, crate::scalar::ScalarBins); 5],
}

impl Grid {
    /// Number of cells.
    pub fn cells(&self) -> usize {
        self.rows * self.cols
    }
}

/// Checks that a `raster` (rows, cols) of pixels reduces to a token `grid` by one integer factor in both
/// directions and returns that factor; errors name `key`.
pub fn downsampling(key: &str, raster: [usize; 2], grid: [usize; 2]) -> Result<usize> {
    let even =
        grid.iter().all(|&g| g > 0) && raster[0].is_multiple_of(grid[0]) && raster[1].is_multiple_of(grid[1]);
    if even && raster[0] / grid[0] == raster[1] / grid[1] {
        return Ok(raster[0] / grid[0]);
    }
    Err(ModalityError::Config {
        key: key.into(),
        message: format!("grid {grid:?} must divide the raster {raster:?} by one factor in both directions"),
    })
}

/// The token interface of a modality: how many tokens it puts in a frame and which ids they use.
///
/// Content ids are `0..vocab_size`; that range includes the modality's own special values (the agent
/// modality's category and pad ids, for example). The start and end ids that wrap the block in a frame lie
/// outside it, by default `vocab_size` and `vocab_size + 1`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModalitySpec {
    /// Unique name within a frame (for example `ego`).
    pub name: String,
    /// Which implementation built it (for example `ego`); two modalities may share a kind.
    pub kind: String,
    /// Number of content ids.
    pub vocab_size: u32,
    /// Content tokens per frame.
    pub tokens_per_frame: usize,
    /// Id of the block's start token.
    pub start_id: u32,
    /// Id of the block's end token.
    pub end_id: u32,
    /// Id meaning "nothing here", when the modality has one (inside the content ids).
    pub pad_id: Option<u32>,
    /// Spatial arrangement of the tokens, when they form a grid.
    pub grid: Option<Grid>,
    /// Bins of the leading content tokens, when they are discretised scalars (the ego action's dx, dy,
    /// dθ), so that models can decode them to values.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bins: Vec<crate::scalar::ScalarBins>,
    /// Content ids `0..ordinal` are bins of ordered scalar values, neighbouring ids holding neighbouring
    /// values (the ego action's and the agents' value bins); 0 when the ids are unordered codes. Models
    /// may use it to start nearby bins with similar embeddings.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ordinal: u32,
    /// The slot layout, when the tokens are slots of tracked objects.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracks: Option<Tracks>,
    /// The slot layout, when the tokens are slots of stop points.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stops: Option<crate::stops::Stops>,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

impl ModalitySpec {
    /// A spec with start/end ids just past the content ids, no pad and no grid.
    pub fn new(
        name: impl Into<String>,
        kind: impl Into<String>,
        vocab_size: u32,
        tokens_per_frame: usize,
    ) -> Self {
        Self {
            name: name.into(),
            kind: kind.into(),
            vocab_size,
            tokens_per_frame,
            start_id: vocab_size,
            end_id: vocab_size + 1,
            pad_id: None,
            grid: None,
            bins: Vec::new(),
            ordinal: 0,
            tracks: None,
            stops: None,
        }
    }

    /// Sets the pad id.
    pub fn with_pad(mut self, pad: u32) -> Self {
        self.pad_id = Some(pad);
        self
    }

    /// Sets the spatial grid.
    pub fn with_grid(mut self, rows: usize, cols: usize) -> Self {
        self.grid = Some(Grid {
            rows,
            cols,
            cell_m: None,
        });
        self
    }

    /// Sets a metric bird's-eye grid of `cell_m` metres per cell.
    pub fn with_metric_grid(mut self, rows: usize, cols: usize, cell_m: f64) -> Self {
        self.grid = Some(Grid {
            rows,
            cols,
            cell_m: Some(cell_m),
        });
        self
    }

    /// Sets the bins of the leading content tokens.
    pub fn with_bins(mut self, bins: Vec<crate::scalar::ScalarBins>) -> Self {
        self.bins = bins;
        self
    }

    /// Declares the tokens as slots of tracked objects.
    pub fn with_tracks(mut self, tracks: Tracks) -> Self {
        self.tracks = Some(tracks);
        self
    }

    /// Declares the tokens as slots of stop points.
    pub fn with_stops(mut self, stops: crate::stops::Stops) -> Self {
        self.stops = Some(stops);
        self
    }

    /// Declares content ids `0..ordinal` as ordered scalar bins.
    pub fn with_ordinal(mut self, ordinal: u32) -> Self {
        self.ordinal = ordinal;
        self
    }

    /// Checks that `ids` is one frame's content block: exactly `tokens_per_frame` ids (what
    /// [`Modality::detokenize`](crate::Modality::detokenize) receives).
    pub fn check_frame_ids(&self, ids: &[u32]) -> Result<()> {
        if ids.len() != self.tokens_per_frame {
            return Err(ModalityError::TokenCount {
                modality: self.name.clone(),
                expected: self.tokens_per_frame,
                actual: ids.len(),
            });
        }
        Ok(())
    }

    /// Size of an embedding table that covers content, start and end ids.
    pub fn embed_vocab(&self) -> u32 {
        self.vocab_size.max(self.start_id + 1).max(self.end_id + 1)
    }

    /// Checks that the spec is self-consistent.
    pub fn validate(&self) -> Result<()> {
        let fail = |reason: String| {
            Err(ModalityError::InvalidSpec {
                modality: self.name.clone(),
                reason,
            })
        };
        let name_ok = !self.name.is_empty()
            && self
                .name
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '-');
        if !name_ok {
            return fail("names use lower-case letters, digits, `_` and `-`".into());
        }
        if self.vocab_size == 0 || self.tokens_per_frame == 0 {
            return fail(format!(
                "vocabulary {} and tokens per frame {} must both be positive",
                self.vocab_size, self.tokens_per_frame
            ));
        }
        if self.start_id < self.vocab_size || self.end_id < self.vocab_size || self.start_id == self.end_id {
            return fail(format!(
                "start id {} and end id {} must differ and lie outside the content ids 0..{}",
                self.start_id, self.end_id, self.vocab_size
            ));
        }
        if let Some(pad) = self.pad_id.filter(|&p| p >= self.vocab_size) {
            return fail(format!(
                "pad id {pad} is not a content id (0..{})",
                self.vocab_size
            ));
        }
        if self.ordinal > self.vocab_size {
            return fail(format!(
                "ordinal ids 0..{} exceed the content ids 0..{}",
                self.ordinal, self.vocab_size
            ));
        }
        if let Some(g) = self.grid.filter(|g| g.cells() != self.tokens_per_frame) {
            return fail(format!(
                "grid {}×{} does not hold {} tokens",
                g.rows, g.cols, self.tokens_per_frame
            ));
        }
        if let Some(st) = &self.stops {
            st.check(self.tokens_per_frame, self.vocab_size).or_else(fail)?;
        }
        Ok(())
    }
}

/// A pre-trained token embedding matrix (for example a VQ codebook), row `i` for content id `i`.
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    entries: usize,
    dim: usize,
    weights: Vec<f32>,
}

impl Codebook {
    /// A codebook of `entries` rows of `dim` values, row-major.
    pub fn new(modality: &str, entries: usize, dim: usize, weights: Vec<f32>) -> Result<Self> {
        if entries == 0 || dim == 0 || weights.len() != entries * dim {
            return Err(ModalityError::InvalidSpec {
                modality: modality.into(),
                reason: format!("codebook {entries}×{dim} given {} values", weights.len()),
            });
        }
        Ok(Self {
            entries,
            dim,
            weights,
        })
    }

    /// Number of rows.
    pub fn entries(&self) -> usize {
        self.entries
    }

    /// Values per row.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// All values, row-major.
    pub fn weights(&self) -> &[f32] {
        &self.weights
    }

    /// Row `i`, if it exists.
    pub fn row(&self, i: usize) -> Option<&[f32]> {
        self.weights.get(i * self.dim..(i + 1) * self.dim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_catches_inconsistent_specs() {
        assert!(ModalitySpec::new("ego", "ego", 1024, 3).validate().is_ok());
        assert_eq!(ModalitySpec::new("ego", "ego", 1024, 3).embed_vocab(), 1026);
        let cases = [
            (ModalitySpec::new("Ego", "ego", 10, 3), "lower-case"),
            (ModalitySpec::new("e", "e", 0, 3), "positive"),
            (ModalitySpec::new("e", "e", 10, 4).with_grid(3, 2), "grid"),
            (ModalitySpec::new("e", "e", 10, 3).with_pad(10), "pad id 10"),
            (
                ModalitySpec::new("e", "e", 10, 3).with_ordinal(11),
                "ordinal ids 0..11",
            ),
            (
                ModalitySpec {
                    start_id: 5,
                    ..ModalitySpec::new("e", "e", 10, 3)
                },
                "start id 5",
            ),
        ];
        for (spec, needle) in cases {
            let err = spec.validate().unwrap_err().to_string();
            assert!(
                err.contains(needle) && err.contains(&format!("`{}`", spec.name)),
                "{err}"
            );
        }
    }

    #[test]
    fn downsampling_factors() {
        assert_eq!(downsampling("k", [256, 256], [32, 32]).unwrap(), 8);
        assert_eq!(downsampling("k", [256, 512], [16, 32]).unwrap(), 16);
        for grid in [[30, 32], [32, 16], [0, 32]] {
            assert!(
                downsampling("modality.map.grid", [256, 256], grid)
                    .unwrap_err()
                    .to_string()
                    .contains("modality.map.grid")
            );
        }
    }

    #[test]
    fn codebook_rows() {
        let cb = Codebook::new("map", 3, 2, vec![0., 1., 2., 3., 4., 5.]).unwrap();
        assert_eq!(cb.row(1), Some(&[2.0f32, 3.0][..]));
        assert_eq!(cb.row(3), None);
        assert!(Codebook::new("map", 3, 2, vec![0.0; 5]).is_err());
    }
}
