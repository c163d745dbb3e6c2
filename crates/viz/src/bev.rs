//! The bird's-eye view of a frame: map layers, agent boxes with velocity arrows, the ego box, and the
//! marks modalities add.

use crate::image::Rgb;
use umgen_modality::Mark;
use umgen_render::MapView;
use umgen_scene::{Agent, AgentCategory, MapLayer, MapRaster};

/// Background of the BEV.
pub const BACKGROUND: [u8; 3] = [28, 30, 36];
/// Ego box colour.
pub const EGO: [u8; 3] = [222, 44, 44];

/// Colour of a map layer.
pub fn layer_colour(l: MapLayer) -> [u8; 3] {
    match l {
        MapLayer::Intersection => [58, 66, 92],
        MapLayer::Lane => [92, 96, 104],
        MapLayer::LaneConnector => [110, 92, 128],
        MapLayer::Crosswalk => [196, 196, 182],
        MapLayer::LaneDivider => [236, 200, 70],
        MapLayer::StopLine => [232, 84, 72],
    }
}

/// Colour of an agent box: cars green, pedestrians and cyclists orange (as in the paper's figures).
pub fn agent_colour(c: AgentCategory) -> [u8; 3] {
    match c {
        AgentCategory::Vehicle => [64, 196, 96],
        AgentCategory::Pedestrian => [250, 150, 40],
        AgentCategory::Cyclist => [250, 200, 40],
    }
}

/// Paint order: areas first, markings last.
const ORDER: [MapLayer; 6] = [
    MapLayer::Intersection,
    MapLayer::Lane,
    MapLayer::LaneConnector,
    MapLayer::Crosswalk,
    MapLayer::LaneDivider,
    MapLayer::StopLine,
];

/// Draws the BEV of one frame: `raster` (whose channels are `view.layers`, at `view.size`) with the
/// agents on top, and the ego box (`ego_size` = length, width) at the origin.
pub fn draw_bev(view: &MapView, raster: Option<&MapRaster>, agents: &[Agent], ego_size: [f64; 2]) -> Rgb {
    let [rows, cols] = view.size;
    let mut img = Rgb::filled(cols, rows, BACKGROUND);
    if let Some(raster) = raster {
        for layer in ORDER {
            let Some(k) = view.layers.iter().position(|&l| l == layer) else {
                continue;
            };
            let (Some(ch), true) = (raster.channel(k), raster.height == rows && raster.width == cols) else {
                continue;
            };
            for (p, &v) in img.pixels.iter_mut().zip(ch) {
                if v > 127 {
                    *p = layer_colour(layer);
                }
            }
        }
    }
    let scale = cols as f64 / view.extent_m;
    for a in agents {
        let colour = agent_colour(a.category);
        let corners = box_corners(view, a.x, a.y, a.heading, a.length, a.width);
        img.canvas().fill_polygon(&corners, colour);
        let dark = colour.map(|v| v / 2);
        let mut outline = corners.to_vec();
        outline.push(corners[0]);
        img.canvas().stroke(&outline, 1.0, dark);
        // The front edge, so that headings read at a glance.
        img.line(corners[0], corners[1], 2.0, [245, 245, 245]);
        let c = view.ego_to_pixel([a.x, a.y]);
        let tip = view.ego_to_pixel([a.x + a.vx, a.y + a.vy]);
        if (a.vx.hypot(a.vy)) * scale > 2.0 {
            img.arrow(c, tip, 1.5, 4.0, [235, 235, 255]);
        }
    }
    let ego = box_corners(view, 0.0, 0.0, 0.0, ego_size[0], ego_size[1]);
    img.canvas().fill_polygon(&ego, EGO);
    img.line(ego[0], ego[1], 2.0, [255, 255, 255]);
    img
}

/// Draws modality marks (ego frame, metres) onto a BEV of `view`; widths and radii below a pixel are drawn
/// one pixel wide, so that small marks stay visible.
pub fn draw_marks(img: &mut Rgb, view: &MapView, marks: &[Mark]) {
    let scale = view.size[1] as f64 / view.extent_m;
    for m in marks {
        match *m {
            Mark::Line {
                from,
                to,
                width,
                colour,
            } => img.line(
                view.ego_to_pixel(from),
                view.ego_to_pixel(to),
                (width * scale).max(1.0),
                colour,
            ),
            Mark::Dot { at, radius, colour } => {
                let [cx, cy] = view.ego_to_pixel(at);
                let r = (radius * scale).max(1.0);
                let disc: Vec<[f64; 2]> = (0..16)
                    .map(|k| {
                        let a = f64::from(k) * std::f64::consts::TAU / 16.0;
                        [cx + r * a.cos(), cy + r * a.sin()]
                    })
                    .collect();
                img.canvas().fill_polygon(&disc, colour);
            }
        }
    }
}

/// Pixel corners of a box: front-left, front-right, rear-right, rear-left.
fn box_corners(view: &MapView, x: f64, y: f64, heading: f64, length: f64, width: f64) -> [[f64; 2]; 4] {
    let (s, c) = heading.sin_cos();
    [[1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0]].map(|[sl, sw]| {
        let (lx, ly) = (sl * length / 2.0, sw * width / 2.0);
        view.ego_to_pixel([x + c * lx - s * ly, y + s * lx + c * ly])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_land_where_the_view_puts_their_ego_coordinates() {
        let view = MapView::default();
        let mut img = Rgb::filled(view.size[1], view.size[0], BACKGROUND);
        let (red, green) = ([200, 10, 10], [10, 200, 10]);
        let marks = [
            Mark::Dot {
                at: [20.0, 10.0],
                radius: 1.5,
                colour: red,
            },
            Mark::Line {
                from: [-20.0, -10.0],
                to: [-20.0, 10.0],
                width: 1.0,
                colour: green,
            },
        ];
        draw_marks(&mut img, &view, &marks);
        let at = |p: [f64; 2]| {
            let [c, r] = view.ego_to_pixel(p);
            img.get(r as usize, c as usize).unwrap()
        };
        assert_eq!(at([20.0, 10.0]), red);
        assert_eq!(at([-20.0, 0.0]), green);
        assert_eq!(at([-20.0, 5.0]), green);
        // The mirror images and the space between stay background.
        assert_eq!(at([20.0, -10.0]), BACKGROUND);
        assert_eq!(at([20.0, 13.0]), BACKGROUND);
        assert_eq!(at([0.0, 0.0]), BACKGROUND);
    }
}
