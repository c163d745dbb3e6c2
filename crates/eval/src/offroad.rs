//! Whether points lie on a road network's drivable area (its lanes, connectors and intersections), for
//! the off-road rate of agents: a grid of cells lists the polygons whose bounding box reaches each cell,
//! and a point is tested (even–odd rule) against those of its cell only.

use std::collections::HashMap;
use umgen_scene::{Polygon, RoadNetwork};

/// Side of a grid cell (m).
const CELL_M: f64 = 16.0;

/// The drivable area of one road network, indexed.
#[derive(Debug, Clone)]
pub struct Drivable {
    polygons: Vec<Polygon>,
    cells: HashMap<(i64, i64), Vec<usize>>,
}

fn cell(v: f64) -> i64 {
    (v / CELL_M).floor() as i64
}

impl Drivable {
    /// The lanes, connectors and intersections of `network`.
    pub fn new(network: &RoadNetwork) -> Self {
        let polygons: Vec<Polygon> = network
            .lanes
            .iter()
            .chain(&network.connectors)
            .chain(&network.intersections)
            .filter(|p| p.len() >= 3)
            .cloned()
            .collect();
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (i, p) in polygons.iter().enumerate() {
            let [x0, y0, x1, y1] = umgen_scene::bbox(p, 0.0);
            for cx in cell(x0)..=cell(x1) {
                for cy in cell(y0)..=cell(y1) {
                    cells.entry((cx, cy)).or_default().push(i);
                }
            }
        }
        Self { polygons, cells }
    }

    /// Whether the global point `p` lies inside a drivable polygon.
    pub fn contains(&self, p: [f64; 2]) -> bool {
        self.cells
            .get(&(cell(p[0]), cell(p[1])))
            .is_some_and(|ids| ids.iter().any(|&i| inside(p, &self.polygons[i])))
    }
}

/// Even–odd rule: a ray from `p` towards +x crosses the polygon's edges an odd number of times.
fn inside(p: [f64; 2], poly: &[[f64; 2]]) -> bool {
    let mut odd = false;
    let mut j = poly.len() - 1;
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[j]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                odd = !odd;
            }
        }
        j = i;
    }
    odd
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_on_lanes_connectors_and_intersections_are_drivable() {
        let square = |x: f64, y: f64, s: f64| vec![[x, y], [x + s, y], [x + s, y + s], [x, y + s]];
        let network = RoadNetwork {
            id: "t".into(),
            lanes: vec![vec![[0.0, 0.0], [100.0, 0.0], [100.0, 3.5], [0.0, 3.5]]],
            connectors: vec![square(100.0, 0.0, 3.5)],
            // An L-shaped intersection: its bounding box covers (110, 10), the polygon does not.
            intersections: vec![vec![
                [103.5, 0.0],
                [120.0, 0.0],
                [120.0, 4.0],
                [107.0, 4.0],
                [107.0, 20.0],
                [103.5, 20.0],
            ]],
            crosswalks: Vec::new(),
            stop_lines: Vec::new(),
            dividers: Vec::new(),
            sidewalks: vec![square(0.0, 3.5, 2.0)],
        };
        let d = Drivable::new(&network);
        for p in [
            [50.0, 1.0],
            [99.9, 3.4],
            [101.0, 2.0],
            [115.0, 2.0],
            [105.0, 15.0],
        ] {
            assert!(d.contains(p), "{p:?}");
        }
        // Beside the lane, on the sidewalk, in the L's notch, far away.
        for p in [[50.0, -0.5], [1.0, 4.5], [110.0, 10.0], [-500.0, 2.0]] {
            assert!(!d.contains(p), "{p:?}");
        }
    }
}
