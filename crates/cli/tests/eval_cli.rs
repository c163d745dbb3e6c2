//! `umgen eval` over several contexts in one batch, and with the recorded ego actions
//! (`generate --recorded-ego`), on a bundle of the tiny fixture and clips of the bundled SUMO sample.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{eval_test_split, ok, umgen};

use std::path::PathBuf;
use umgen_tests::run_fixture::Fixture;

#[test]
fn eval_pools_several_contexts_and_recorded_ego_isolates_the_agents() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("v", 2).unwrap();
    ok(umgen(&["train", "--config", cfg.to_str().unwrap()]));
    let bf16_dir = fx.dir.path().join("bundle-bf16");
    ok(umgen(&[
        "export",
        "--checkpoint",
        fx.run_dir("v").to_str().unwrap(),
        "--out",
        bf16_dir.to_str().unwrap(),
        "--dtype",
        "bf16",
    ]));
    // Several contexts in one batch (clips of the bundled SUMO sample, whose motion varies): --context,
    // then --contexts' clips of a split; eval pools them, and its constant-velocity baselines (no model in
    // them) are the means of the contexts' own.
    let json =
        |p: PathBuf| -> serde_json::Value { serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap() };
    let sample = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/sumo-sample");
    let sample = sample.to_str().unwrap();
    // Two frames generated into `out` under the scratch directory, with `args` (contexts, options).
    let generate = |out: &str, args: &[&str]| -> PathBuf {
        let out = fx.dir.path().join(out);
        let mut all = vec![
            "generate",
            "--bundle",
            bf16_dir.to_str().unwrap(),
            "--frames",
            "2",
        ];
        all.extend(args);
        all.extend(["--out", out.to_str().unwrap()]);
        ok(umgen(&all));
        out
    };
    let run_gen = |out: &str, contexts: &[&str]| {
        let out = generate(out, contexts);
        eval_test_split(&out, sample);
        out
    };
    let (one, many) = (format!("{sample}:rand-s3/v0:0:2"), format!("{sample}:test:2:2"));
    let multi = run_gen("gen-multi", &["--context", &one, "--contexts", &many]);
    let meta = json(multi.join("meta.json"));
    let ids: Vec<String> = meta["contexts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["clip"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(ids.len(), 3, "{meta}");
    assert_eq!(ids[0], "rand-s3/v0:0");
    let tokens = json(multi.join("tokens.json"));
    assert_eq!(tokens["context_of"], serde_json::json!([0, 1, 2]));
    let report = json(multi.join("eval/report.json"));
    assert_eq!(report["contexts"], 3);
    for h in 0..2 {
        for who in [
            "model",
            "constant_velocity",
            "constant_velocity_binned",
            "constant_acceleration",
            "constant_acceleration_binned",
            "real_state_constant_acceleration",
            "real_state_constant_acceleration_binned",
        ] {
            let at = |k: &str| report["l2"][h][format!("agents_{who}_{k}")].as_f64().unwrap();
            assert!(at("p90") >= at("median"), "{who} at horizon {h}: {report}");
        }
    }
    // Over the horizon: the rollouts' second against the real split; counts recomputed from scenes.json.
    let scenes = json(multi.join("scenes.json"));
    let frames: Vec<Vec<Vec<u64>>> = scenes
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            s["frames"]
                .as_array()
                .unwrap()
                .iter()
                .map(|f| {
                    f["agents"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|a| a["track_id"].as_u64().unwrap())
                        .collect()
                })
                .collect()
        })
        .collect();
    let horizon = &report["horizon"];
    let second = &horizon["seconds"][0]["generated"];
    assert_eq!(
        horizon["seconds"].as_array().unwrap().len(),
        1,
        "2 frames of 0.5 s: {horizon}"
    );
    assert_eq!(second["frames"], 6);
    // With one second generated, the whole horizon pooled is that second, MMD and all.
    assert_eq!(horizon["whole"]["generated"], *second, "{horizon}");
    assert_eq!(horizon["whole"]["mmd"], horizon["seconds"][0]["mmd"]);
    let counts: Vec<usize> = frames.iter().flatten().map(Vec::len).collect();
    let mean = counts.iter().sum::<usize>() as f64 / 6.0;
    assert!(
        (second["agents_mean"].as_f64().unwrap() - mean).abs() < 1e-9,
        "{second}"
    );
    let entries: usize = frames
        .iter()
        .map(|f| f[1].iter().filter(|id| !f[0].contains(id)).count())
        .sum();
    let exits: usize = frames
        .iter()
        .map(|f| f[0].iter().filter(|id| !f[1].contains(id)).count())
        .sum();
    assert_eq!(
        second["entries_per_s"].as_f64(),
        Some(entries as f64 / 1.5),
        "{second}"
    );
    assert_eq!(
        second["exits_per_s"].as_f64(),
        Some(exits as f64 / 1.5),
        "{second}"
    );
    // The counts behind the rates, each rate inside its 95 % interval.
    let c = &second["counts"];
    assert_eq!(
        (c["entries"].as_u64(), c["exits"].as_u64(), c["seconds"].as_f64()),
        (Some(entries as u64), Some(exits as u64), Some(1.5)),
        "{c}"
    );
    // The bundle's agents have a range, so every entry and exit is told inside or across its edge.
    assert!(c["entries_inside"].as_u64().unwrap() <= entries as u64, "{c}");
    assert!(c["exits_inside"].as_u64().unwrap() <= exits as u64, "{c}");
    for (rate, ci) in [(entries, "entries_per_s_95"), (exits, "exits_per_s_95")] {
        let (lo, hi) = (c[ci][0].as_f64().unwrap(), c[ci][1].as_f64().unwrap());
        assert!(lo <= rate as f64 / 1.5 && rate as f64 / 1.5 <= hi, "{ci}: {c}");
    }
    let real = &horizon["real"];
    assert!(real["agents_mean"].as_f64().unwrap() > 1.0, "{real}");
    let total: f64 = real["agents_distribution"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_f64().unwrap())
        .sum();
    assert!((total - 1.0).abs() < 1e-9, "{real}");
    for rate in [
        &real["off_road_rate"],
        &second["off_road_rate"],
        &real["collision_rate"],
    ] {
        assert!((0.0..=1.0).contains(&rate.as_f64().unwrap()), "{horizon}");
    }
    // SUMO's vehicles drive on its lanes: their centres in world coordinates lie on the drivable area.
    assert!(
        real["vehicle_off_road_rate"].as_f64().unwrap() < 0.02,
        "real vehicles off the road: {real}"
    );
    // They keep to it: hardly a vehicle leaves the road between two frames (4 in 9,816 s of the whole
    // test split, at connectors).
    let leaving = &real["counts"]["leaving_road"];
    let per_s = leaving["vehicles"].as_f64().unwrap() / real["counts"]["seconds"].as_f64().unwrap();
    assert!(per_s < 0.01, "{leaving}");
    // SUMO's egos drive on the road too (all but a frame in 10,000 here), so the vehicles of the frames
    // whose ego is on it are nearly all of them.
    let rate = |key: &str| real[key].as_f64().unwrap();
    assert!(rate("ego_off_road_rate") < 1e-3, "{real}");
    assert!(
        (rate("vehicle_off_road_ego_on_rate") - rate("vehicle_off_road_rate")).abs() < 1e-3,
        "{real}"
    );
    assert!(
        real["heading_motion_median_deg"].as_f64().unwrap() < 10.0,
        "real agents drive where they head: {real}"
    );
    assert!(multi.join("eval/horizon.png").exists() || horizon["seconds"].as_array().unwrap().len() < 2);
    let md = std::fs::read_to_string(multi.join("eval/report.md")).unwrap();
    assert!(
        md.contains("## Over the horizon") && md.contains("\n| real | ") && md.contains("\n| 1–1 | "),
        "{md}"
    );
    assert!(
        md.contains("| collision | overlapping ego | onsets/s | onsets at speed into standing |"),
        "{md}"
    );
    // The events table: the second's entry count and its rate over the 1.5 s counted.
    let events = format!("\n| 1 | 1.5 | {entries} | {:.3} [", entries as f64 / 1.5);
    assert!(
        md.contains("## Events per second, with 95 % intervals") && md.contains(&events),
        "{events}: {md}"
    );
    assert!(real["collision_onsets_per_s"].as_f64().unwrap() >= 0.0, "{real}");
    // Real agents seldom touch the ego's box (0.022 of the test split's frames: the box is the official
    // code's ego, larger than SUMO's).
    let on_ego = real["ego_overlap_rate"].as_f64().unwrap();
    assert!(on_ego > 0.0 && on_ego < 0.05, "{real}");
    // SUMO's car-following model brakes for what stands ahead, and its queues drive off again.
    assert!(
        real["approach_braking"].as_f64().unwrap() > 0.8,
        "real vehicles brake on the approach to a standing one: {real}"
    );
    // And most of those still at speed a step before begin to brake (0.67 on the test split).
    assert!(
        real["approach_braking_onset"].as_f64().unwrap() > 0.5,
        "real vehicles begin to brake for a standing one ahead: {real}"
    );
    assert!(real["starts_per_standing_s"].as_f64().unwrap() > 0.0, "{real}");
    assert!(
        md.contains("| approaches/s | braking on approach | braking begun | starts/s |"),
        "{md}"
    );
    assert!(md.contains("| binned const. vel. mean |"), "{md}");
    assert!(
        md.contains("| vehicles off the map | entering off it | of those off, entered off |"),
        "{md}"
    );
    assert!(md.contains("| binned const. acc. mean |"), "{md}");
    assert!(
        md.contains("| onsets/s | leaving the road | leaving/s | of them moving | their turn ° |"),
        "{md}"
    );
    assert!(
        md.contains("| second | share of the window | lane |") && md.contains("| vehicles | off the road |"),
        "{md}"
    );
    assert!(md.contains("| binned real-state const. acc. mean |"), "{md}");
    let singles: Vec<serde_json::Value> = ids
        .iter()
        .enumerate()
        .map(|(k, id)| {
            let one = format!("{sample}:{id}:2");
            let out = run_gen(&format!("gen-one-{k}"), &["--context", &one]);
            // The same clip's context rows as in the batch.
            let rows = |t: &serde_json::Value, s: usize| t["scenes"][s].as_array().unwrap()[..2].to_vec();
            assert_eq!(rows(&json(out.join("tokens.json")), 0), rows(&tokens, k));
            json(out.join("eval/report.json"))
        })
        .collect();
    // The map at the pose: 3 contexts × 2 real frames and 3 scenes × 2 generated frames, every layer of
    // the fixture's map; the three contexts pooled lie between the contexts alone, layer by layer (sums of
    // intersections over sums of unions), which holds only if each context's rows met its own clip's poses.
    let map = &report["map"];
    assert_eq!(map["layers"].as_array().unwrap().len(), 6, "{map}");
    assert_eq!(
        (&map["context"]["frames"], &map["seconds"][0]["frames"]),
        (&6.into(), &6.into()),
        "{map}"
    );
    // Within the context's view: a context frame's cells are all in its own window, so there the IoU is
    // the whole window's; the generated frames' windows lie partly or wholly in the context's.
    let shown = &map["context"]["context_view"];
    assert_eq!(shown["share"].as_f64(), Some(1.0), "{map}");
    assert_eq!(shown["iou"], map["context"]["iou"], "{map}");
    let share = map["seconds"][0]["context_view"]["share"].as_f64().unwrap();
    assert!(share > 0.0 && share <= 1.0, "{map}");
    for layer in 0..6 {
        let alone: Vec<f64> = singles
            .iter()
            .filter_map(|r| r["map"]["context"]["iou"][layer].as_f64())
            .collect();
        let Some(pooled) = map["context"]["iou"][layer].as_f64() else {
            assert!(alone.is_empty(), "layer {layer}: {map}");
            continue;
        };
        assert!((0.0..=1.0).contains(&pooled), "{map}");
        let f1 = map["context"]["f1_within_1px"][layer].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&f1), "{map}");
        let (lo, hi) = alone
            .iter()
            .fold((1.0f64, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(
            lo - 1e-12 <= pooled && pooled <= hi + 1e-12,
            "layer {layer}: {pooled} outside {alone:?}"
        );
    }
    for h in 0..2 {
        for key in ["ego_constant_velocity", "agents_constant_velocity"] {
            let cv: Vec<f64> = singles
                .iter()
                .map(|r| r["l2"][h][key].as_f64().unwrap())
                .collect();
            assert!(cv.iter().any(|v| (v - cv[0]).abs() > 1e-6), "{key}: {cv:?}");
            let pooled = report["l2"][h][key].as_f64().unwrap();
            assert!(
                (pooled - cv.iter().sum::<f64>() / 3.0).abs() < 1e-9,
                "{key}: {pooled} vs {cv:?}"
            );
        }
    }
    // --recorded-ego: the ego follows the clip's recorded actions, so its L2 is only the bins' rounding,
    // far below what the barely trained ego module draws; clips too short for it are refused by name.
    let forced = run_gen("gen-recorded", &["--context", &one, "--recorded-ego"]);
    let recorded = json(forced.join("eval/report.json"));
    assert_eq!(recorded["recorded_ego"], true, "{recorded}");
    for h in 0..2 {
        let e = recorded["l2"][h]["ego_model"].as_f64().unwrap();
        let drawn = singles[0]["l2"][h]["ego_model"].as_f64().unwrap();
        assert!(
            e < 0.05 && e < drawn,
            "horizon {h}: {e} m recorded, {drawn} m drawn"
        );
    }
    // The model against its hint: one step ahead and only with the recorded ego (the hint's bins are the
    // real next ego frame's), every scored agent either on the hint's bins or moved off them.
    let hint = &recorded["l2"][0]["hint"];
    let share = |k: &str| hint[k].as_f64().unwrap_or(0.0);
    assert!(hint["agents"].as_u64().unwrap() > 0, "{hint}");
    assert!(
        (share("followed") + share("departed") - 1.0).abs() < 1e-12,
        "{hint}"
    );
    assert!(share("closer") + share("farther") <= 1.0 + 1e-12, "{hint}");
    assert!(recorded["l2"][1]["hint"].is_null() && report["l2"][0]["hint"].is_null());
    let md = std::fs::read_to_string(forced.join("eval/report.md")).unwrap();
    assert!(md.contains("| agents | on the hint |"), "{md}");
    let out = fx.dir.path().join("gen-refused");
    let refused = |from: &[&str], frames: &str, wants: &[&str]| {
        let mut args = vec!["generate", "--bundle", bf16_dir.to_str().unwrap()];
        args.extend(from);
        args.extend([
            "--frames",
            frames,
            "--recorded-ego",
            "--out",
            out.to_str().unwrap(),
        ]);
        let run = umgen(&args);
        let err = String::from_utf8_lossy(&run.stderr).to_string();
        assert!(!run.status.success(), "{args:?} ran");
        assert!(wants.iter().all(|w| err.contains(w)), "{err}");
    };
    // The sample's clip rand-s3/v0:0 holds 40 frames: 2 of context leave 38 to generate.
    refused(
        &["--context", &one],
        "100000",
        &[
            "--recorded-ego: clip `rand-s3/v0:0`",
            "has 40 frames, 2 of context and 100000 to generate need 100002",
            "(1 of the 1 contexts end too soon; --frames 38 fits every one)",
        ],
    );
    refused(&["--from-scratch"], "1", &["--recorded-ego", "--from-scratch"]);

    // An output brought from another machine: the bundle meta.json names is not here. `--bundle` gives
    // one of the same layout; tokens drawn in another layout are refused, naming both.
    let moved = fx.dir.path().join("gen-moved");
    std::fs::create_dir_all(&moved).unwrap();
    for f in ["meta.json", "tokens.json", "scenes.json"] {
        std::fs::copy(forced.join(f), moved.join(f)).unwrap();
    }
    let mut meta = json(moved.join("meta.json"));
    meta["bundle"] = "/nowhere/bundle".into();
    std::fs::write(moved.join("meta.json"), meta.to_string()).unwrap();
    let eval_moved = |bundle: Option<&str>| {
        let mut args = vec![
            "eval",
            "--generated",
            moved.to_str().unwrap(),
            "--reference",
            sample,
        ];
        args.extend(["--stride", "50"]);
        args.extend(bundle.map(|b| ["--bundle", b]).into_iter().flatten());
        umgen(&args)
    };
    let run = eval_moved(None);
    let err = String::from_utf8_lossy(&run.stderr).to_string();
    assert!(!run.status.success() && err.contains("/nowhere/bundle"), "{err}");
    ok(eval_moved(Some(bf16_dir.to_str().unwrap())));
    assert_eq!(
        json(moved.join("eval/report.json"))["horizon"],
        recorded["horizon"],
        "the same tokens decoded with a bundle of the same layout"
    );
    let mut tokens = json(moved.join("tokens.json"));
    tokens["fingerprint"] = "0".repeat(64).into();
    std::fs::write(moved.join("tokens.json"), tokens.to_string()).unwrap();
    let run = eval_moved(Some(bf16_dir.to_str().unwrap()));
    let err = String::from_utf8_lossy(&run.stderr).to_string();
    assert!(!run.status.success(), "tokens of another layout evaluated");
    assert!(
        err.contains(&format!("drawn with the layout {}", "0".repeat(64))),
        "{err}"
    );

    // --recorded map,image: the generated frames hold the clip's own map and image codes of those frames,
    // the codes that a context of the same clip reaching over them is tokenized to.
    let tokens = |out: &str, args: &[&str]| -> Vec<Vec<u64>> {
        let t = json(generate(out, args).join("tokens.json"));
        serde_json::from_value(t["scenes"][0].clone()).unwrap()
    };
    let given = tokens(
        "gen-given",
        &["--context", &one, "--recorded", "map", "--recorded", "image,ego"],
    );
    let real = tokens("gen-real", &["--context", &format!("{sample}:rand-s3/v0:0:4")]);
    let layout = umgen::Bundle::open(&bf16_dir).unwrap().manifest.layout;
    let segments = layout["segments"].as_array().unwrap();
    for name in ["map", "image", "ego"] {
        let seg = segments.iter().find(|s| s["modality"] == name).unwrap();
        let at = seg["offset"].as_u64().unwrap() as usize;
        let span = at..at + seg["tokens"].as_u64().unwrap() as usize;
        for f in 2..4 {
            assert_eq!(given[f][span.clone()], real[f][span.clone()], "{name}, frame {f}");
        }
    }
    let drawn = tokens("gen-drawn", &["--context", &one, "--seed", "3"]);
    assert_ne!(drawn[2..], real[2..4], "the model alone draws the clip's frames");
    let run = umgen(&[
        "generate",
        "--bundle",
        bf16_dir.to_str().unwrap(),
        "--context",
        &one,
        "--recorded",
        "lights",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&run.stderr).to_string();
    assert!(!run.status.success());
    assert!(
        err.contains(
            "--recorded lights: `lights` is none of this model's modalities, ego, map, agent, image"
        ),
        "{err}"
    );
}
