//! `umgen generate --map-memory` on a bundle of the tiny fixture and clips of the bundled SUMO sample:
//! with the ego held still, every pixel of the generated maps is held and the map codes stay those of
//! the first generated frame, where the same rollout without the memory draws its map anew each frame;
//! a recorded map is refused by name. `umgen eval` of the held rollout without its scenes.json decodes
//! tokens.json to the same report.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{LOOSE_DRAW, eval_test_split, fixture_bundle, ok, umgen};

use std::path::{Path, PathBuf};
use umgen_tests::run_fixture::Fixture;

fn json(p: PathBuf) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// The map codes of each generated frame of each scene in `out`.
fn generated_maps(out: &Path, bundle: &Path) -> Vec<Vec<Vec<u32>>> {
    let layout = umgen::Bundle::open(bundle).unwrap().manifest.layout;
    let seg = layout["segments"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["modality"] == "map")
        .unwrap()
        .clone();
    let at = seg["offset"].as_u64().unwrap() as usize;
    let span = at..at + seg["tokens"].as_u64().unwrap() as usize;
    let tokens = json(out.join("tokens.json"));
    let context = tokens["context_frames"].as_u64().unwrap() as usize;
    let scenes: Vec<Vec<Vec<u32>>> = serde_json::from_value(tokens["scenes"].clone()).unwrap();
    scenes
        .iter()
        .map(|rows| rows[context..].iter().map(|r| r[span.clone()].to_vec()).collect())
        .collect()
}

#[test]
fn a_standing_egos_held_map_stays_put() {
    let fx = Fixture::new().unwrap();
    // Odd bin counts centred on zero, so that the forced standstill decodes to no motion at all.
    let bundle = fixture_bundle(&fx, "m", |mut text| {
        assert!(!text.contains("[modality.ego]"), "{text}");
        text.push_str("[modality.ego]\nbins = 5\ndx = [-1.0, 1.0]\ndy = [-1.0, 1.0]\ndtheta = [-0.5, 0.5]\n");
        text
    });
    let control = fx.dir.path().join("standing.toml");
    std::fs::write(
        &control,
        "[[ego]]\nfrom = 0\nto = 5\ndx = 0.0\ndy = 0.0\ndtheta = 0.0\n",
    )
    .unwrap();
    let sample = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/sumo-sample");
    let contexts = format!("{}:test:4:2", sample.to_str().unwrap());
    let run = |out: &str, memory: bool| -> (PathBuf, String) {
        let out = fx.dir.path().join(out);
        let mut args = vec![
            "generate",
            "--bundle",
            bundle.to_str().unwrap(),
            "--contexts",
            &contexts,
            "--frames",
            "5",
            "--control",
            control.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        // The barely trained model's maps change.
        args.extend(LOOSE_DRAW);
        if memory {
            args.push("--map-memory");
        }
        let log = ok(umgen(&args));
        (out, log)
    };
    let (free, log) = run("free", false);
    assert!(!log.contains("map memory"), "{log}");
    assert!(json(free.join("meta.json"))["map_memory"].is_null());
    let drawn = generated_maps(&free, &bundle);
    assert!(
        drawn.iter().any(|frames| frames.windows(2).any(|w| w[0] != w[1])),
        "without the memory, the map is drawn anew: {drawn:?}"
    );
    let (held, log) = run("held", true);
    assert!(
        log.contains("map memory: 100.0 % of the generated frames' map held"),
        "{log}"
    );
    let meta = json(held.join("meta.json"));
    let m = &meta["map_memory"];
    assert_eq!(m["frames"].as_u64(), Some(4 * 5), "{m}");
    // The fixture's map raster is 32 × 32.
    assert_eq!(m["pixels"].as_u64(), Some(4 * 5 * 32 * 32), "{m}");
    assert_eq!(m["held"], m["pixels"], "{m}");
    assert_eq!(m["codes"].as_u64(), Some(4 * 5 * 16), "{m}");
    let maps = generated_maps(&held, &bundle);
    assert_eq!(maps.len(), 4);
    for (s, frames) in maps.iter().enumerate() {
        assert_eq!(frames.len(), 5);
        for (k, f) in frames.iter().enumerate() {
            assert_eq!(f, &frames[0], "scene {s}, generated frame {k}");
        }
    }
    // `umgen eval` decodes tokens.json itself where scenes.json was not kept, to the same report.
    eval_test_split(&held, sample.to_str().unwrap());
    let report = json(held.join("eval/report.json"));
    std::fs::remove_file(held.join("scenes.json")).unwrap();
    let log = eval_test_split(&held, sample.to_str().unwrap());
    assert!(
        log.contains("no scenes.json; decoding the 4 scenes of tokens.json"),
        "{log}"
    );
    assert_eq!(json(held.join("eval/report.json")), report);
    // A recorded map is the clip's, not the model's: nothing to hold.
    let refused = umgen(&[
        "generate",
        "--bundle",
        bundle.to_str().unwrap(),
        "--context",
        &format!("{}:rand-s3/v0:0:2", sample.to_str().unwrap()),
        "--recorded",
        "map",
        "--map-memory",
        "--out",
        fx.dir.path().join("recorded").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(
        err.contains("--map-memory holds the map the model draws; with `map` recorded it draws none"),
        "{err}"
    );
}
