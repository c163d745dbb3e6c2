//! The BEV map raster: road elements rasterised around an ego pose.

use crate::fill::Canvas;
use umgen_scene::{MapLayer, MapRaster, Marking, Pose2, RoadNetwork, boxes_overlap};

/// Geometry of the BEV view: a square of `extent_m` metres centred on the ego, `size` pixels, x forward
/// = up (row 0 at the front), y left = left (column 0 at the left).
#[derive(Debug, Clone, PartialEq)]
pub struct MapView {
    /// Side of the square (m).
    pub extent_m: f64,
    /// Rows and columns.
    pub size: [usize; 2],
    /// Which layer goes into which channel.
    pub layers: Vec<MapLayer>,
}

impl Default for MapView {
    /// The paper's view: 128 m, 256×256 (0.5 m per pixel), all six layers.
    fn default() -> Self {
        Self {
            extent_m: 128.0,
            size: [256, 256],
            layers: MapLayer::ALL.to_vec(),
        }
    }
}

impl MapView {
    /// Metres per pixel along rows and columns.
    pub fn resolution(&self) -> [f64; 2] {
        [
            self.extent_m / self.size[0] as f64,
            self.extent_m / self.size[1] as f64,
        ]
    }

    /// Pixel coordinates (x = column, y = row, continuous) of a point in the ego frame.
    pub fn ego_to_pixel(&self, p: [f64; 2]) -> [f64; 2] {
        let [rr, rc] = self.resolution();
        let half = self.extent_m / 2.0;
        [(half - p[1]) / rc, (half - p[0]) / rr]
    }

    /// The ego-frame point at the centre of pixel (row, col).
    pub fn pixel_to_ego(&self, row: usize, col: usize) -> [f64; 2] {
        let [rr, rc] = self.resolution();
        let half = self.extent_m / 2.0;
        [half - (row as f64 + 0.5) * rr, half - (col as f64 + 0.5) * rc]
    }

    /// The channels of the layers vehicles drive on (lanes, intersections, lane connectors).
    pub fn drivable_channels(&self) -> Vec<usize> {
        let drivable = [MapLayer::Lane, MapLayer::Intersection, MapLayer::LaneConnector];
        (0..self.layers.len())
            .filter(|&i| drivable.contains(&self.layers[i]))
            .collect()
    }

    /// Whether the cell of `map` (a raster of this view) holding the ego-frame point `p` is set (above
    /// 127, as the map modality reads it) in one of `channels`; `None` outside the raster.
    pub fn covers(&self, map: &MapRaster, channels: &[usize], p: [f64; 2]) -> Option<bool> {
        let [col, row] = self.ego_to_pixel(p).map(f64::floor);
        let inside = |v: f64, n: usize| (0.0..n as f64).contains(&v).then_some(v as usize);
        let (row, col) = (inside(row, map.height)?, inside(col, map.width)?);
        let plane = map.height * map.width;
        Some(channels.iter().any(|&c| {
            map.data
                .get(c * plane + row * map.width + col)
                .is_some_and(|&v| v > 127)
        }))
    }

    /// The raster of `network` around `pose`; each covered cell is 255.
    pub fn render(&self, network: &RoadNetwork, pose: &Pose2) -> MapRaster {
        let [rows, cols] = self.size;
        let mut raster = MapRaster::zeros(self.layers.len(), rows, cols);
        let reach = self.extent_m * std::f64::consts::FRAC_1_SQRT_2 + 1.0;
        let view = [pose.x - reach, pose.y - reach, pose.x + reach, pose.y + reach];
        let bounds = network.bounds();
        let min_px = self.resolution()[0].max(self.resolution()[1]);
        for (k, layer) in self.layers.iter().enumerate() {
            let Some(cells) = raster.channel_mut(k) else {
                continue;
            };
            let mut canvas = Canvas {
                cells,
                width: cols,
                height: rows,
            };
            let to_px = |p: &[f64; 2]| self.ego_to_pixel(pose.to_local(*p));
            let mut polys = |items: &[Vec<[f64; 2]>], boxes: &[[f64; 4]]| {
                for (poly, b) in items.iter().zip(boxes) {
                    if boxes_overlap(b, &view) {
                        let px: Vec<[f64; 2]> = poly.iter().map(to_px).collect();
                        canvas.fill_polygon(&px, 255);
                    }
                }
            };
            match layer {
                MapLayer::Lane => polys(&network.lanes, &bounds.lanes),
                MapLayer::LaneConnector => polys(&network.connectors, &bounds.connectors),
                MapLayer::Intersection => polys(&network.intersections, &bounds.intersections),
                MapLayer::Crosswalk => {
                    for (cw, b) in network.crosswalks.iter().zip(&bounds.crosswalks) {
                        if boxes_overlap(b, &view) {
                            let px: Vec<[f64; 2]> = cw.polygon.iter().map(to_px).collect();
                            canvas.fill_polygon(&px, 255);
                        }
                    }
                }
                MapLayer::StopLine | MapLayer::LaneDivider => {
                    let (marks, boxes): (&[Marking], &[[f64; 4]]) = if *layer == MapLayer::StopLine {
                        (&network.stop_lines, &bounds.stop_lines)
                    } else {
                        (&network.dividers, &bounds.dividers)
                    };
                    for (m, b) in marks.iter().zip(boxes) {
                        if boxes_overlap(b, &view) {
                            let px: Vec<[f64; 2]> = m.line.iter().map(to_px).collect();
                            // At least one pixel wide, so that thin markings stay continuous.
                            canvas.stroke(&px, (m.width / min_px).max(1.0), 255);
                        }
                    }
                }
            }
        }
        raster
    }
}
