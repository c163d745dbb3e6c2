//! The network parser and the map raster against hand-computed positions.

use super::fixture;
use umgen_data::sumo::parse_net;
use umgen_render::MapView;
use umgen_scene::{MapLayer, Pose2};

#[test]
fn network_elements_are_where_sumo_puts_them() {
    let n = parse_net(&fixture("tiny.net.xml"), "tiny").unwrap();
    let net = &n.network;
    assert_eq!(net.lanes.len(), 4);
    assert_eq!(
        (
            net.connectors.len(),
            net.crosswalks.len(),
            net.intersections.len()
        ),
        (1, 1, 1)
    );
    assert_eq!(net.sidewalks.len(), 2, "one sidewalk lane and one walking area");
    // AB_0: centre line y = -4.8, width 3.2 → the strip y ∈ [-6.4, -3.2].
    assert_eq!(
        net.lanes[0],
        vec![[0.0, -3.2], [100.0, -3.2], [100.0, -6.4], [0.0, -6.4]]
    );
    // Dividers: between AB's lanes (y = -3.2), AB's centre line to the opposite road (y = 0), BA's (y = 3.2).
    let mut ys: Vec<f64> = net.dividers.iter().map(|d| d.line[0][1]).collect();
    ys.sort_by(f64::total_cmp);
    assert_eq!(ys, vec![-3.2, 0.0, 3.2]);
    // Stop lines: AB ends at traffic light B; BA ends at dead end A and has none.
    assert_eq!(net.stop_lines.len(), 2);
    for s in &net.stop_lines {
        assert_eq!(s.line.len(), 2);
        assert!(s.line.iter().all(|p| (p[0] - 99.75).abs() < 1e-9), "{s:?}");
    }
    assert_eq!(net.crosswalks[0].direction, [0.0, 1.0]);
    assert!(n.lanes.contains("AB_0") && n.lanes.contains(":B_0_0") && n.edges.contains("SW"));
}

#[test]
fn raster_places_the_lane_under_the_ego_and_the_junction_ahead() {
    let net = parse_net(&fixture("tiny.net.xml"), "tiny").unwrap().network;
    // Ego on AB_0 at x = 50, facing east: 0.5 m per pixel, row 0 at the front, column 0 on the left.
    let r = MapView::default().render(&net, &Pose2::new(50.0, -4.8, 0.0));
    let at = |l: MapLayer, row, col| r.get(l.channel(), row, col).unwrap();
    assert_eq!(at(MapLayer::Lane, 128, 128), 255, "the ego's lane under it");
    assert_eq!(at(MapLayer::Lane, 108, 128), 255, "10 m ahead");
    // The road spans global y ∈ [-6.4, 6.4]: local y ∈ [-1.6, 11.2] → columns 105.6 .. 131.2.
    assert_eq!(at(MapLayer::Lane, 128, 105), 0);
    assert_eq!(at(MapLayer::Lane, 128, 106), 255);
    assert_eq!(at(MapLayer::Lane, 128, 130), 255);
    assert_eq!(at(MapLayer::Lane, 128, 132), 0);
    // Divider at global y = -3.2 → local y = 1.6 → column 124.8.
    assert_eq!(at(MapLayer::LaneDivider, 128, 124), 255);
    assert_eq!(at(MapLayer::LaneDivider, 128, 128), 0);
    // Stop line at global x = 99.75 → 49.75 m ahead → row 28.5.
    assert_eq!(at(MapLayer::StopLine, 28, 128), 255);
    assert_eq!(at(MapLayer::StopLine, 40, 128), 0);
    // Junction B: global x ∈ [100, 106.4] → rows 15.2 .. 28; the crossing at x = 102 ± 2 → rows 20 .. 28.
    assert_eq!(at(MapLayer::Intersection, 20, 118), 255);
    assert_eq!(at(MapLayer::Intersection, 30, 118), 0);
    assert_eq!(at(MapLayer::Crosswalk, 24, 118), 255);
    assert_eq!(at(MapLayer::Crosswalk, 18, 118), 0);
    // Nothing behind the dead end A (50 m behind the ego: row 228).
    assert_eq!(at(MapLayer::Lane, 240, 128), 0);
}
