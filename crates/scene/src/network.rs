//! Road networks as vector geometry: the source of truth from which map rasters and camera views are
//! rendered around any ego pose.

use serde::{Deserialize, Serialize};

/// A closed polygon in global coordinates (metres); the last vertex connects back to the first.
pub type Polygon = Vec<[f64; 2]>;

/// An open polyline in global coordinates (metres).
pub type Polyline = Vec<[f64; 2]>;

/// The six map raster channels, in channel order (paper supplementary B.2.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MapLayer {
    /// Drivable lane surfaces.
    Lane,
    /// Stop lines where lanes enter junctions.
    StopLine,
    /// Pedestrian crossings.
    Crosswalk,
    /// Junction areas.
    Intersection,
    /// Lines between neighbouring lanes of one road.
    LaneDivider,
    /// Lane connectors through junctions.
    LaneConnector,
}

impl MapLayer {
    /// Every layer in channel order.
    pub const ALL: [MapLayer; 6] = [
        MapLayer::Lane,
        MapLayer::StopLine,
        MapLayer::Crosswalk,
        MapLayer::Intersection,
        MapLayer::LaneDivider,
        MapLayer::LaneConnector,
    ];

    /// Channel index.
    pub fn channel(self) -> usize {
        self as usize
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        [
            "lane",
            "stop_line",
            "crosswalk",
            "intersection",
            "lane_divider",
            "lane_connector",
        ][self as usize]
    }
}

/// A pedestrian crossing: its area and the direction people walk across it (unit vector), along which
/// zebra stripes run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Crosswalk {
    /// Area.
    pub polygon: Polygon,
    /// Walking direction (unit vector).
    pub direction: [f64; 2],
}

/// A line marking with a physical width (metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Marking {
    /// Centre line of the marking.
    pub line: Polyline,
    /// Width (m).
    pub width: f64,
}

/// A road network's drawable geometry.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RoadNetwork {
    /// Network id, unique within a dataset.
    pub id: String,
    /// Drivable lane surfaces (outside junctions).
    pub lanes: Vec<Polygon>,
    /// Lane connectors through junctions.
    pub connectors: Vec<Polygon>,
    /// Pedestrian crossings.
    pub crosswalks: Vec<Crosswalk>,
    /// Junction areas.
    pub intersections: Vec<Polygon>,
    /// Stop lines.
    pub stop_lines: Vec<Marking>,
    /// Lines between neighbouring lanes.
    pub dividers: Vec<Marking>,
    /// Sidewalks and walking areas (drawn by the camera, not a map channel).
    pub sidewalks: Vec<Polygon>,
}

/// Axis-aligned bounding boxes of every element, for culling elements outside a view.
#[derive(Debug, Clone, PartialEq)]
pub struct Bounds {
    /// Box of each element of [`RoadNetwork::lanes`], `[min_x, min_y, max_x, max_y]`.
    pub lanes: Vec<[f64; 4]>,
    /// Boxes of connectors.
    pub connectors: Vec<[f64; 4]>,
    /// Boxes of crosswalks.
    pub crosswalks: Vec<[f64; 4]>,
    /// Boxes of intersections.
    pub intersections: Vec<[f64; 4]>,
    /// Boxes of stop lines (grown by half their width).
    pub stop_lines: Vec<[f64; 4]>,
    /// Boxes of dividers (grown by half their width).
    pub dividers: Vec<[f64; 4]>,
    /// Boxes of sidewalks.
    pub sidewalks: Vec<[f64; 4]>,
    /// Box of the whole network.
    pub all: [f64; 4],
}

/// The bounding box of points, grown by `margin`; an empty set gives an inverted (empty) box.
pub fn bbox(points: &[[f64; 2]], margin: f64) -> [f64; 4] {
    let mut b = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    for p in points {
        b = [b[0].min(p[0]), b[1].min(p[1]), b[2].max(p[0]), b[3].max(p[1])];
    }
    [b[0] - margin, b[1] - margin, b[2] + margin, b[3] + margin]
}

/// Whether two boxes overlap.
pub fn boxes_overlap(a: &[f64; 4], b: &[f64; 4]) -> bool {
    a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3]
}

impl RoadNetwork {
    /// Element boxes (one pass over the points; cheap next to rendering).
    pub fn bounds(&self) -> Bounds {
        {
            let polys = |v: &[Polygon]| v.iter().map(|p| bbox(p, 0.0)).collect::<Vec<_>>();
            let marks = |v: &[Marking]| v.iter().map(|m| bbox(&m.line, m.width / 2.0)).collect::<Vec<_>>();
            let b = Bounds {
                lanes: polys(&self.lanes),
                connectors: polys(&self.connectors),
                crosswalks: self.crosswalks.iter().map(|c| bbox(&c.polygon, 0.0)).collect(),
                intersections: polys(&self.intersections),
                stop_lines: marks(&self.stop_lines),
                dividers: marks(&self.dividers),
                sidewalks: polys(&self.sidewalks),
                all: [0.0; 4],
            };
            let mut all = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            let groups = [
                &b.lanes,
                &b.connectors,
                &b.crosswalks,
                &b.intersections,
                &b.stop_lines,
                &b.dividers,
                &b.sidewalks,
            ];
            for bb in groups.into_iter().flatten() {
                all = [
                    all[0].min(bb[0]),
                    all[1].min(bb[1]),
                    all[2].max(bb[2]),
                    all[3].max(bb[3]),
                ];
            }
            Bounds { all, ..b }
        }
    }

    /// Number of drawable elements.
    pub fn element_count(&self) -> usize {
        self.lanes.len()
            + self.connectors.len()
            + self.crosswalks.len()
            + self.intersections.len()
            + self.stop_lines.len()
            + self.dividers.len()
            + self.sidewalks.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_cover_elements_and_markings_grow_by_half_width() {
        let net = RoadNetwork {
            id: "n".into(),
            lanes: vec![vec![[0.0, 0.0], [10.0, 0.0], [10.0, 3.0]]],
            dividers: vec![Marking {
                line: vec![[0.0, 5.0], [10.0, 5.0]],
                width: 0.2,
            }],
            ..RoadNetwork::default()
        };
        let b = net.bounds();
        assert_eq!(b.lanes[0], [0.0, 0.0, 10.0, 3.0]);
        assert!((b.dividers[0][1] - 4.9).abs() < 1e-12 && (b.dividers[0][3] - 5.1).abs() < 1e-12);
        assert!((b.all[3] - 5.1).abs() < 1e-12);
        assert!(boxes_overlap(&b.lanes[0], &[5.0, 2.0, 20.0, 20.0]));
        assert!(!boxes_overlap(&b.lanes[0], &[11.0, 0.0, 20.0, 20.0]));
        assert_eq!(net.clone(), net);
        assert_eq!(MapLayer::ALL.map(MapLayer::channel), [0, 1, 2, 3, 4, 5]);
    }
}
