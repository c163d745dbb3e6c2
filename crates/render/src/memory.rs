//! A map held fixed in the world: what a view's rasters showed, kept in cells of the world plane, so that
//! ground seen once reads the same from every later pose.
//!
//! A rollout draws its map afresh in every frame, in the ego's coordinates; with nothing tying one
//! frame's map to the last, the drawing drifts even where the context showed the real road.
//! [`MapMemory`] holds each world cell at the value it first had ([`MapMemory::remember`]) and lays
//! the held cells over a new frame's map ([`MapMemory::recall`]), the rest of the frame as drawn.
//!
//! Cells are the view's pixels, aligned with the world's axes: at a pose whose heading is a multiple of
//! a right angle and whose position lies on the cell grid, a raster goes in and comes out unchanged.
//! At other poses each pixel reads the cell under its centre, and each cell the pixel under its
//! centre (nearest neighbour, both ways), so a cell is never filled from two pixels and ground seen
//! at one pose and read at another moves by less than a pixel.

use crate::MapView;
use std::collections::HashMap;
use umgen_scene::{MapRaster, Pose2};

/// Why a view cannot be held.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MemoryError {
    /// The cells are square; the view's pixels are not.
    #[error("map memory: the view's pixels are {0:?} m, and the memory's cells are square")]
    NotSquare([f64; 2]),
    /// A cell keeps its layers as the bits of a `u16`.
    #[error("map memory: the view has {0} layers, and a cell holds at most 16")]
    TooManyLayers(usize),
    /// A raster that is not of this view.
    #[error("map memory: a {got:?} raster (channels, rows, columns), and the view's are {want:?}")]
    Raster {
        /// The raster's channels, rows and columns.
        got: [usize; 3],
        /// The view's.
        want: [usize; 3],
    },
}

/// Cells of the world plane, each holding the layers a raster of `view` first showed there.
#[derive(Debug, Clone)]
pub struct MapMemory {
    view: MapView,
    /// Side of a cell (m): the view's pixel.
    cell: f64,
    /// Per cell (column along x, row along y), bit `c` set where channel `c` covers it.
    cells: HashMap<(i64, i64), u16>,
}

impl MapMemory {
    /// An empty memory for rasters of `view`.
    pub fn new(view: MapView) -> Result<Self, MemoryError> {
        let res = view.resolution();
        if (res[0] - res[1]).abs() > 1e-9 * res[0].abs().max(1.0) {
            return Err(MemoryError::NotSquare(res));
        }
        if view.layers.len() > 16 {
            return Err(MemoryError::TooManyLayers(view.layers.len()));
        }
        Ok(Self {
            view,
            cell: res[0],
            cells: HashMap::new(),
        })
    }

    /// Cells held.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// Whether no cell is held.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    fn check(&self, raster: &MapRaster) -> Result<(), MemoryError> {
        let want = [self.view.layers.len(), self.view.size[0], self.view.size[1]];
        let got = [raster.channels, raster.height, raster.width];
        if got == want {
            Ok(())
        } else {
            Err(MemoryError::Raster { got, want })
        }
    }

    fn cell_of(&self, w: [f64; 2]) -> (i64, i64) {
        (
            (w[0] / self.cell).floor() as i64,
            (w[1] / self.cell).floor() as i64,
        )
    }

    /// Writes the cells that `raster`, seen from the ego `pose` (in world coordinates), covers and the
    /// memory does not hold yet; cells held keep their value. A cell whose centre lies in the raster
    /// takes the pixel there; a cell that only a pixel's centre lies in (at the raster's border) takes
    /// that pixel, so that every pixel of the view at `pose` reads a held cell afterwards. Returns how
    /// many cells were new.
    pub fn remember(&mut self, raster: &MapRaster, pose: &Pose2) -> Result<usize, MemoryError> {
        self.check(raster)?;
        let [rows, cols] = self.view.size;
        // The world cells under the view's square: the box around its four corners.
        let corners = [(0, 0), (0, cols), (rows, 0), (rows, cols)].map(|(r, c)| {
            let e = self.view.pixel_to_ego(r, c);
            let [rr, rc] = self.view.resolution();
            // pixel_to_ego gives centres: step back half a pixel to the corner.
            pose.to_parent([e[0] + rr / 2.0, e[1] + rc / 2.0])
        });
        let lo = self.cell_of([
            corners.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min),
            corners.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min),
        ]);
        let hi = self.cell_of([
            corners.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max),
            corners.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max),
        ]);
        let mut new = 0;
        for i in lo.0..=hi.0 {
            for j in lo.1..=hi.1 {
                if self.cells.contains_key(&(i, j)) {
                    continue;
                }
                let centre = [(i as f64 + 0.5) * self.cell, (j as f64 + 0.5) * self.cell];
                let [col, row] = self.view.ego_to_pixel(pose.to_local(centre)).map(f64::floor);
                if !(0.0..rows as f64).contains(&row) || !(0.0..cols as f64).contains(&col) {
                    continue;
                }
                self.cells
                    .insert((i, j), bits_at(raster, row as usize * cols + col as usize));
                new += 1;
            }
        }
        for r in 0..rows {
            for c in 0..cols {
                let cell = self.cell_of(pose.to_parent(self.view.pixel_to_ego(r, c)));
                if let std::collections::hash_map::Entry::Vacant(e) = self.cells.entry(cell) {
                    e.insert(bits_at(raster, r * cols + c));
                    new += 1;
                }
            }
        }
        Ok(new)
    }

    /// The raster of the view at `pose`: each pixel whose centre lies in a held cell takes that cell's
    /// layers (255 or 0), every other pixel `fresh`'s value. Returns it and how many pixels were held.
    pub fn recall(&self, pose: &Pose2, fresh: &MapRaster) -> Result<(MapRaster, usize), MemoryError> {
        self.check(fresh)?;
        let mut out = fresh.clone();
        let [rows, cols] = self.view.size;
        let plane = rows * cols;
        let mut held = 0;
        for r in 0..rows {
            for c in 0..cols {
                let w = pose.to_parent(self.view.pixel_to_ego(r, c));
                let Some(&bits) = self.cells.get(&self.cell_of(w)) else {
                    continue;
                };
                held += 1;
                for ch in 0..out.channels {
                    out.data[ch * plane + r * cols + c] = if bits & (1 << ch) != 0 { 255 } else { 0 };
                }
            }
        }
        Ok((out, held))
    }
}

/// The layers set (above 127) at pixel `at` (row-major) of `raster`, as bits.
fn bits_at(raster: &MapRaster, at: usize) -> u16 {
    let plane = raster.height * raster.width;
    (0..raster.channels)
        .filter(|&c| raster.data[c * plane + at] > 127)
        .fold(0u16, |b, c| b | (1 << c))
}

#[cfg(test)]
#[path = "memory_tests.rs"]
mod tests;
