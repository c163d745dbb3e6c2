//! `umgen generate --entering-on-road` on a bundle of the tiny fixture and clips of the bundled SUMO
//! sample: `umgen eval`, which decodes the frames' map codes on its own, finds no vehicle entering off
//! its frame's map where the rule ran, and finds some in the same rollout without it.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{LOOSE_DRAW, eval_test_split, fixture_bundle, ok, umgen};

use std::path::PathBuf;
use umgen_tests::run_fixture::Fixture;

fn json(p: PathBuf) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn entering_vehicles_stay_on_their_frames_own_map() {
    let fx = Fixture::new().unwrap();
    // More slots than the clips' nearest agents fill, so that the rollouts' agents can enter.
    let bundle = fixture_bundle(&fx, "v", |text| {
        assert!(text.contains("max_agents = 4"), "{text}");
        text.replace("max_agents = 4", "max_agents = 16")
    });
    let sample = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/sumo-sample");
    let sample = sample.to_str().unwrap();
    let contexts = format!("{sample}:test:8:2");
    // Six frames of eight clips, drawn alike, with and without the rule; `umgen eval` on each.
    let run = |out: &str, rule: bool| -> (serde_json::Value, serde_json::Value) {
        let out = fx.dir.path().join(out);
        let mut args = vec![
            "generate",
            "--bundle",
            bundle.to_str().unwrap(),
            "--contexts",
            &contexts,
            "--frames",
            "6",
            "--out",
            out.to_str().unwrap(),
        ];
        // The barely trained model's agents come and go.
        args.extend(LOOSE_DRAW);
        if rule {
            args.push("--entering-on-road");
        }
        let log = ok(umgen(&args));
        assert_eq!(log.contains("road rule: emptied"), rule, "{log}");
        eval_test_split(&out, sample);
        (json(out.join("meta.json")), json(out.join("eval/report.json")))
    };
    // Entering vehicles off the frame's own map, and entering vehicles, over the generated seconds.
    let off_map = |report: &serde_json::Value| -> (f64, usize) {
        let seconds = report["map"]["seconds"].as_array().unwrap();
        seconds.iter().fold((0.0, 0), |(off, n), s| {
            let share = s["entering_off_map"].as_f64();
            (off + share.unwrap_or(0.0), n + usize::from(share.is_some()))
        })
    };
    let (meta, report) = run("free", false);
    assert!(meta["entering_on_road"].is_null(), "{meta}");
    let (free_off, free_seconds) = off_map(&report);
    assert!(
        free_off > 0.0,
        "the barely trained model places some entering vehicles off its map: {}",
        report["map"]
    );
    let (meta, report) = run("road", true);
    let road = &meta["entering_on_road"];
    let (tested, dropped) = (
        road["tested"].as_u64().unwrap(),
        road["dropped"].as_u64().unwrap(),
    );
    assert!(dropped > 0 && dropped <= tested, "{road}");
    assert!(road["beyond_map"].as_u64().unwrap() <= tested - dropped, "{road}");
    let (road_off, road_seconds) = off_map(&report);
    assert!(free_seconds > 0 && road_seconds > 0, "{}", report["map"]);
    assert_eq!(road_off, 0.0, "{}", report["map"]);
    // The rule tests the agents the model draws: with the agents recorded it is refused by name.
    let out = fx.dir.path().join("recorded");
    let refused = umgen(&[
        "generate",
        "--bundle",
        bundle.to_str().unwrap(),
        "--context",
        &format!("{sample}:rand-s3/v0:0:2"),
        "--recorded",
        "agent",
        "--entering-on-road",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success());
    assert!(
        err.contains("--entering-on-road tests the agents the model draws"),
        "{err}"
    );
}
