//! The camera against hand-computed projections.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use umgen_render::{Camera, agent_colour};
use umgen_scene::{Agent, AgentCategory, Pose2, RoadNetwork};

fn car(x: f64, y: f64, category: AgentCategory) -> Agent {
    Agent {
        track_id: 0,
        category,
        x,
        y,
        z: 0.75,
        vx: 0.0,
        vy: 0.0,
        vz: 0.0,
        heading: 0.0,
        length: 4.0,
        width: 2.0,
        height: 1.5,
    }
}

fn road() -> RoadNetwork {
    RoadNetwork {
        lanes: vec![vec![[-50.0, -2.0], [200.0, -2.0], [200.0, 2.0], [-50.0, 2.0]]],
        ..RoadNetwork::default()
    }
}

#[test]
fn projection_and_horizon() {
    let cam = Camera::default();
    // A point far along the optical axis lands on the image centre.
    let pitch = cam.pitch_deg.to_radians();
    let d = 100.0;
    let p = [cam.mount_x + d * pitch.cos(), 0.0, cam.height_m - d * pitch.sin()];
    let [c, r, z] = cam.project(p);
    assert!((c - 256.0).abs() < 1e-9 && (r - 128.0).abs() < 1e-9 && (z - d).abs() < 1e-9);
    // The horizon sits f·tan(pitch) above the centre: sky above it, ground below.
    let horizon = 128.0 - cam.focal_px() * pitch.tan();
    let img = cam.render(&road(), &Pose2::default(), &[]);
    let sky = img.pixel(horizon as usize - 3, 10).unwrap();
    let ground = img.pixel(horizon as usize + 40, 10).unwrap();
    assert!(sky[2] > 200 && ground[2] < 150, "sky {sky:?} ground {ground:?}");
    // The road straight ahead is darker than the grass beside it.
    let road_px = img.pixel(250, 256).unwrap();
    let grass_px = img.pixel(250, 5).unwrap();
    assert!(road_px[1] < grass_px[1], "{road_px:?} vs {grass_px:?}");
}

#[test]
fn boxes_appear_where_projected_and_occlude_in_depth_order() {
    let cam = Camera::default();
    let near = car(12.0, 0.0, AgentCategory::Vehicle);
    let img = cam.render(&road(), &Pose2::default(), &[near]);
    // The back face's centre projects to the middle columns; its colour is the shaded vehicle colour.
    let [c, r, _] = cam.project([near.x - 2.0, 0.0, 0.75]);
    let px = img.pixel(r as usize, c as usize).unwrap();
    let base = agent_colour(AgentCategory::Vehicle);
    assert!(
        px[2] > px[0] && px[2] > px[1],
        "{px:?} should be vehicle blue like {base:?}"
    );
    // A pedestrian hidden behind the car does not show through.
    let mut hidden = car(20.0, 0.0, AgentCategory::Pedestrian);
    (hidden.length, hidden.width, hidden.height, hidden.z) = (0.4, 0.5, 1.0, 0.5);
    let both = cam.render(&road(), &Pose2::default(), &[hidden, near]);
    assert_eq!(both.pixel(r as usize, c as usize), Some(px));
    // Agents behind the camera draw nothing; the same inputs give the same pixels.
    let behind = cam.render(
        &road(),
        &Pose2::default(),
        &[car(-10.0, 0.0, AgentCategory::Vehicle)],
    );
    assert_eq!(behind, cam.render(&road(), &Pose2::default(), &[]));
    assert_eq!(both, cam.render(&road(), &Pose2::default(), &[near, hidden]));
}
