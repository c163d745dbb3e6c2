//! Where training rasters come from, and how batches are drawn from them.

use crate::error::{Result, VqError};
use rand::{Rng, SeedableRng, rngs::StdRng};

/// A collection of rasters, each `C × H × W` values already normalised for the model (binary layers in
/// {0, 1}, colours in [-1, 1]). Implementations render on demand.
pub trait RasterSource: Send + Sync {
    /// `[C, H, W]`.
    fn shape(&self) -> [usize; 3];
    /// Number of rasters.
    fn len(&self) -> usize;
    /// Whether there are none.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Raster `index`.
    fn item(&self, index: usize) -> std::result::Result<Vec<f32>, String>;
}

/// Rasters `indices` rendered on up to `threads` threads, concatenated in order.
pub fn render(source: &dyn RasterSource, indices: &[usize], threads: usize) -> Result<Vec<f32>> {
    let threads = threads.clamp(1, indices.len().max(1));
    let chunk = indices.len().div_ceil(threads).max(1);
    let parts: Vec<std::result::Result<Vec<f32>, String>> = std::thread::scope(|s| {
        let handles: Vec<_> = indices
            .chunks(chunk)
            .map(|ids| {
                s.spawn(move || {
                    let mut out = Vec::new();
                    for &i in ids {
                        out.extend(source.item(i)?);
                    }
                    Ok(out)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err("a rendering thread panicked".into()))
            })
            .collect()
    });
    let [c, h, w] = source.shape();
    let mut out = Vec::with_capacity(indices.len() * c * h * w);
    for p in parts {
        out.extend(p.map_err(VqError::Data)?);
    }
    if out.len() != indices.len() * c * h * w {
        return Err(VqError::Data(format!(
            "rasters of {} values, expected {c}×{h}×{w}",
            out.len() / indices.len().max(1)
        )));
    }
    Ok(out)
}

/// The batch of step `step`: `n` indices drawn uniformly with replacement, a function of (seed, step)
/// only, so that a resumed run sees the same batches.
pub fn batch_indices(len: usize, seed: u64, step: u64, n: usize) -> Vec<usize> {
    let mut rng = StdRng::seed_from_u64(seed ^ step.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    (0..n).map(|_| rng.random_range(0..len.max(1))).collect()
}

/// An in-memory source, for tests and small experiments.
#[derive(Debug, Clone)]
pub struct MemorySource {
    shape: [usize; 3],
    items: Vec<Vec<f32>>,
}

impl MemorySource {
    /// Rasters of one shape.
    pub fn new(shape: [usize; 3], items: Vec<Vec<f32>>) -> Result<Self> {
        let n = shape.iter().product::<usize>();
        if let Some(bad) = items.iter().position(|i| i.len() != n) {
            return Err(VqError::Input(format!(
                "raster {bad} has {} values, the shape {shape:?} needs {n}",
                items[bad].len()
            )));
        }
        Ok(Self { shape, items })
    }
}

impl RasterSource for MemorySource {
    fn shape(&self) -> [usize; 3] {
        self.shape
    }

    fn len(&self) -> usize {
        self.items.len()
    }

    fn item(&self, index: usize) -> std::result::Result<Vec<f32>, String> {
        self.items
            .get(index)
            .cloned()
            .ok_or_else(|| format!("no raster {index}"))
    }
}
