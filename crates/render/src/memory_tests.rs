#![allow(clippy::unwrap_used)]

use super::{MapMemory, MemoryError};
use crate::MapView;
use umgen_scene::{MapLayer, MapRaster, Pose2, RoadNetwork};

/// A 32 m view of 32×32 pixels (1 m each), all six layers.
fn view() -> MapView {
    MapView {
        extent_m: 32.0,
        size: [32, 32],
        layers: MapLayer::ALL.to_vec(),
    }
}

/// A cross of two 6 m wide roads through the origin, an intersection box at the crossing, and a
/// crosswalk: shapes with edges in several directions.
fn network() -> RoadNetwork {
    RoadNetwork {
        lanes: vec![
            vec![[-100.0, -3.0], [100.0, -3.0], [100.0, 3.0], [-100.0, 3.0]],
            vec![[-3.0, -100.0], [3.0, -100.0], [3.0, 100.0], [-3.0, 100.0]],
            vec![[10.0, 10.0], [40.0, 25.0], [37.0, 31.0], [7.0, 16.0]],
        ],
        intersections: vec![vec![[-6.0, -6.0], [6.0, -6.0], [6.0, 6.0], [-6.0, 6.0]]],
        ..Default::default()
    }
}

fn set(r: &MapRaster) -> usize {
    r.data.iter().filter(|&&v| v > 127).count()
}

#[test]
fn an_aligned_pose_returns_the_raster_unchanged() {
    let v = view();
    let pose = Pose2::new(4.0, -7.0, 0.0);
    let raster = v.render(&network(), &pose);
    let mut m = MapMemory::new(v.clone()).unwrap();
    assert_eq!(m.remember(&raster, &pose).unwrap(), 32 * 32);
    // Remembered again: nothing new.
    assert_eq!(m.remember(&raster, &pose).unwrap(), 0);
    let blank = MapRaster::zeros(6, 32, 32);
    let (back, held) = m.recall(&pose, &blank).unwrap();
    assert_eq!(held, 32 * 32);
    assert_eq!(back, raster);
    assert!(set(&raster) > 100, "the test network covers the view");
}

#[test]
fn ground_seen_from_one_pose_reads_as_the_network_from_another() {
    let v = view();
    let net = network();
    let first = Pose2::new(0.0, 0.0, 0.0);
    // 10 m ahead and 4 m left, whole pixels: an exact shift of the raster.
    let second = Pose2::new(10.0, 4.0, 0.0);
    let mut m = MapMemory::new(v.clone()).unwrap();
    m.remember(&v.render(&net, &first), &first).unwrap();
    let truth = v.render(&net, &second);
    let fresh = MapRaster::zeros(6, 32, 32);
    let (back, held) = m.recall(&second, &fresh).unwrap();
    // The two squares overlap in 22 × 28 pixels.
    assert_eq!(held, 22 * 28);
    // Held pixels are the network's; the rest are `fresh`'s (zero).
    let plane = 32 * 32;
    for r in 0..32 {
        for c in 0..32 {
            let inside = r >= 10 && c >= 4;
            for ch in 0..6 {
                let got = back.data[ch * plane + r * 32 + c];
                let want = if inside {
                    truth.data[ch * plane + r * 32 + c]
                } else {
                    0
                };
                assert_eq!(got, want, "channel {ch}, pixel ({r}, {c})");
            }
        }
    }
}

#[test]
fn a_turned_pose_reads_the_network_to_within_a_pixel() {
    let v = view();
    let net = network();
    let first = Pose2::new(0.3, -0.2, 0.1);
    let second = Pose2::new(5.0, 3.0, 0.6);
    let mut m = MapMemory::new(v.clone()).unwrap();
    let seen = v.render(&net, &first);
    let new = m.remember(&seen, &first).unwrap();
    // Every pixel's worth of ground, and the cells at the turned square's edges.
    assert!((1000..=1100).contains(&new), "{new} cells");
    // Every pixel of the first view reads a held cell, most of them their own value.
    let (again, all) = m.recall(&first, &MapRaster::zeros(6, 32, 32)).unwrap();
    assert_eq!(all, 32 * 32);
    let same = again.data.iter().zip(&seen.data).filter(|(a, b)| a == b).count();
    assert!(
        same * 100 > 97 * seen.data.len(),
        "{same} of {} values",
        seen.data.len()
    );
    let truth = v.render(&net, &second);
    let (back, held) = m.recall(&second, &MapRaster::zeros(6, 32, 32)).unwrap();
    assert!(held > 500, "{held} pixels held");
    // Held pixels agree with the network rendered at the second pose, but for edge pixels.
    let plane = 32 * 32;
    let (mut differ, mut edge_ok) = (0, 0);
    for r in 0..32 {
        for c in 0..32 {
            let ch = MapLayer::Lane.channel();
            let (got, want) = (
                back.data[ch * plane + r * 32 + c],
                truth.data[ch * plane + r * 32 + c],
            );
            let w = second.to_parent(v.pixel_to_ego(r, c));
            if first_sees(&v, &first, w) && got != want {
                differ += 1;
                // A differing pixel lies within 1.5 pixels of a lane edge: a neighbour differs.
                let near = (r.saturating_sub(1)..=(r + 1).min(31))
                    .flat_map(|rr| (c.saturating_sub(1)..=(c + 1).min(31)).map(move |cc| (rr, cc)))
                    .any(|(rr, cc)| truth.data[ch * plane + rr * 32 + cc] != want);
                edge_ok += usize::from(near);
            }
        }
    }
    assert!(differ * 20 < held, "{differ} of {held} held pixels differ");
    assert_eq!(differ, edge_ok, "every differing pixel is at an edge");
}

/// Whether the view at `pose` covers the world point `w` (away from its border by half a pixel).
fn first_sees(v: &MapView, pose: &Pose2, w: [f64; 2]) -> bool {
    let [col, row] = v.ego_to_pixel(pose.to_local(w));
    (0.5..31.5).contains(&col) && (0.5..31.5).contains(&row)
}

#[test]
fn held_cells_keep_their_first_value() {
    let v = view();
    let pose = Pose2::default();
    let mut m = MapMemory::new(v.clone()).unwrap();
    let mut road = MapRaster::zeros(6, 32, 32);
    road.data.iter_mut().for_each(|x| *x = 255);
    m.remember(&road, &pose).unwrap();
    // A later, empty drawing of the same ground changes nothing.
    assert_eq!(m.remember(&MapRaster::zeros(6, 32, 32), &pose).unwrap(), 0);
    let (back, _) = m.recall(&pose, &MapRaster::zeros(6, 32, 32)).unwrap();
    assert_eq!(back, road);
    assert_eq!(m.len(), 32 * 32);
}

#[test]
fn views_and_rasters_it_cannot_hold_are_refused() {
    let mut v = view();
    v.size = [32, 16];
    assert!(matches!(MapMemory::new(v), Err(MemoryError::NotSquare(_))));
    let m = MapMemory::new(view()).unwrap();
    let err = m
        .recall(&Pose2::default(), &MapRaster::zeros(3, 32, 32))
        .unwrap_err();
    assert_eq!(
        err,
        MemoryError::Raster {
            got: [3, 32, 32],
            want: [6, 32, 32]
        }
    );
    assert!(err.to_string().contains("[3, 32, 32]"));
}
