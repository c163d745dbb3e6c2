//! Whether generated map codes show the road where the ego is: per layer, the intersection over union of
//! a decoded map raster with the raster rendered from the scene's road network at the same ego pose.
//! Frames are pooled by summing their intersections and unions, so a frame without a layer neither helps
//! nor hurts that layer, and a layer set in no frame has no value rather than a perfect one.

use umgen_scene::MapRaster;

/// Two rasters of different shapes were compared.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("map rasters differ in shape: decoded {decoded:?}, rendered {rendered:?} (channels, rows, columns)")]
pub struct ShapeMismatch {
    /// Shape of the decoded raster.
    pub decoded: [usize; 3],
    /// Shape of the rendered raster.
    pub rendered: [usize; 3],
}

/// Intersections and unions of each layer's set cells, summed over the frames added.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LayerIou {
    intersections: Vec<u64>,
    unions: Vec<u64>,
    frames: usize,
}

fn shape(r: &MapRaster) -> [usize; 3] {
    [r.channels, r.height, r.width]
}

impl LayerIou {
    /// Adds one frame's `decoded` and `rendered` rasters (a cell is set above 127, as the map modality
    /// reads its rasters).
    pub fn add(&mut self, decoded: &MapRaster, rendered: &MapRaster) -> Result<(), ShapeMismatch> {
        if shape(decoded) != shape(rendered) || decoded.data.len() != rendered.data.len() {
            return Err(ShapeMismatch {
                decoded: shape(decoded),
                rendered: shape(rendered),
            });
        }
        let channels = decoded.channels;
        if self.intersections.len() < channels {
            self.intersections.resize(channels, 0);
            self.unions.resize(channels, 0);
        }
        let cells = decoded.height * decoded.width;
        for c in 0..channels {
            let range = c * cells..(c + 1) * cells;
            for (&a, &b) in decoded.data[range.clone()].iter().zip(&rendered.data[range]) {
                let (a, b) = (a > 127, b > 127);
                self.intersections[c] += u64::from(a && b);
                self.unions[c] += u64::from(a || b);
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// Frames added.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Each layer's pooled IoU; `None` for a layer that neither raster set in any frame.
    pub fn ious(&self) -> Vec<Option<f64>> {
        self.intersections
            .iter()
            .zip(&self.unions)
            .map(|(&i, &u)| (u > 0).then(|| i as f64 / u as f64))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn raster(channels: usize, set: &[(usize, usize, usize)]) -> MapRaster {
        let mut r = MapRaster::zeros(channels, 4, 4);
        for &(c, y, x) in set {
            r.data[c * 16 + y * 4 + x] = 255;
        }
        r
    }

    #[test]
    fn pooled_over_frames_per_layer() {
        let mut iou = LayerIou::default();
        // Frame 1, layer 0: 2 cells each, 1 shared: 1 / 3. Layer 1: the same 1 cell: 1 / 1.
        let a = raster(3, &[(0, 0, 0), (0, 0, 1), (1, 2, 2)]);
        let b = raster(3, &[(0, 0, 1), (0, 1, 1), (1, 2, 2)]);
        iou.add(&a, &b).unwrap();
        assert_eq!(iou.ious(), vec![Some(1.0 / 3.0), Some(1.0), None]);
        // Frame 2, layer 0: decoded only (0 of 1); layer 1: nothing. Pooled: 1 / 4 and still 1 / 1.
        iou.add(&raster(3, &[(0, 3, 3)]), &raster(3, &[])).unwrap();
        assert_eq!(iou.ious(), vec![Some(0.25), Some(1.0), None]);
        assert_eq!(iou.frames(), 2);
        // A raster against itself agrees everywhere it is set.
        let mut same = LayerIou::default();
        same.add(&a, &a).unwrap();
        assert_eq!(same.ious(), vec![Some(1.0), Some(1.0), None]);
    }

    #[test]
    fn refuses_rasters_of_different_shapes() {
        let e = LayerIou::default()
            .add(&raster(3, &[]), &raster(2, &[]))
            .unwrap_err();
        assert_eq!(e.decoded, [3, 4, 4]);
        assert!(e.to_string().contains("[2, 4, 4]"), "{e}");
    }
}
