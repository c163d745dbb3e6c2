//! Scene clips written as a dataset read back as the same frames.

use std::path::Path;
use umgen_data::{Dataset, write_scene_dataset};

#[test]
fn a_clip_written_as_a_dataset_reads_back_as_the_same_frames() {
    let sample = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/sumo-sample");
    let data = Dataset::open(&sample).unwrap();
    let clips: Vec<_> = [0, 400]
        .iter()
        .map(|&k| data.read_window(k, 0, 12, 1).unwrap())
        .collect();
    assert!(
        clips
            .iter()
            .all(|c| c.frames.iter().any(|f| !f.agents.is_empty()))
    );
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scenes");
    let index = write_scene_dataset(&out, &clips, "scene", "generated").unwrap();
    assert_eq!(index.clips.len(), 2);
    let back = Dataset::open(&out).unwrap();
    for (k, want) in clips.iter().enumerate() {
        let got = back.read_clip(k).unwrap();
        assert_eq!(got.frames.len(), want.frames.len());
        assert_eq!(
            got.network.as_ref().map(|n| n.id.clone()),
            want.network.as_ref().map(|n| n.id.clone())
        );
        for (i, (g, w)) in got.frames.iter().zip(&want.frames).enumerate() {
            let d = (g.ego.x - w.ego.x).abs() + (g.ego.y - w.ego.y).abs();
            assert!(d < 1e-2, "clip {k} frame {i}: ego moved by {d}");
            // The first frame's action needs the step before the clip, which the new log does not have.
            if i > 0 {
                let a = (g.action.dx - w.action.dx).abs() + (g.action.dtheta - w.action.dtheta).abs();
                assert!(a < 1e-3, "clip {k} frame {i}: action differs by {a}");
            }
            assert_eq!(g.agents.len(), w.agents.len(), "clip {k} frame {i}");
            let key = |a: &umgen_scene::Agent| ((a.x * 100.0).round() as i64, (a.y * 100.0).round() as i64);
            let (mut ga, mut wa) = (g.agents.clone(), w.agents.clone());
            ga.sort_by_key(key);
            wa.sort_by_key(key);
            for (x, y) in ga.iter().zip(&wa) {
                let e = (x.x - y.x).abs() + (x.y - y.y).abs() + (x.vx - y.vx).abs() + (x.vy - y.vy).abs();
                assert!(e < 1e-2, "clip {k} frame {i}: agent differs by {e}");
                assert_eq!((x.category, x.length, x.width), (y.category, y.length, y.width));
            }
        }
    }
    // A second write into the same directory is refused, naming it.
    let err = write_scene_dataset(&out, &clips, "scene", "generated").unwrap_err();
    assert!(err.to_string().contains("already holds a dataset"), "{err}");
}
