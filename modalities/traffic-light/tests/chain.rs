//! The plug-in's own binary end to end on clips of the bundled SUMO sample, on the CPU: `umgen-lights`
//! trains the tiny five-modality model, exports, generates, evaluates and draws it; the decoded light states
//! of the context frames are SUMO's; generated frames carry decoded lights; the stock catalog refuses the
//! bundle, naming the kind; `viz --config` draws the lights in their colours; the PyTorch runner's logits
//! and greedy frames are umgen's with the agents braking for red lights (`backbone.track_stops`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::Command;
use umgen::Bundle;
use umgen::data::{Dataset, LightState};
use umgen::modality::{ModalityCatalog, ModalityRegistry};
use umgen::scene::{Extra, Frame, SceneClip};
use umgen_modality_traffic_light::{KIND, TrafficLight, colour};

/// Context frames per generated scene.
const CONTEXT: usize = 4;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Runs `umgen-lights` from the workspace root (the config's tokenizer paths are relative to it) and
/// returns its log, asserting success.
fn lights(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_umgen-lights"))
        .args(args)
        .current_dir(workspace())
        .env("NO_COLOR", "1")
        .env_remove("UMGEN_LOG")
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "umgen-lights {args:?}: {log}");
    log
}

/// `tests/python/check_runner.py` on `bundle` and umgen's greedy `tokens`, where the suite's Python
/// (`UMGEN_TB_PYTHON`, set by `.ci/run`) is given.
fn python_runner_check(bundle: &Path, tokens: &Path) {
    let Ok(python) = std::env::var("UMGEN_TB_PYTHON") else {
        return;
    };
    let out = Command::new(python)
        .arg(workspace().join("tests/python/check_runner.py"))
        .args([bundle, tokens])
        .env("PYTHONPATH", workspace().join("runners/python"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "check_runner.py: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The heads of a frame: x, y, heading, state code.
fn heads(f: &Frame) -> Vec<[f32; 4]> {
    match f.extras.get("signals") {
        Some(Extra::F32(v)) => v.chunks(4).map(|h| [h[0], h[1], h[2], h[3]]).collect(),
        other => panic!("no heads: {other:?}"),
    }
}

/// The bundled sample reduced to `train` clips of the train split and two of the test split whose first
/// frames see red and green heads, so that the test runs in a minute.
fn sample_subset(dir: &Path, train: usize) -> PathBuf {
    let sample = workspace().join("data/sumo-sample");
    let ds = Dataset::open(&sample).unwrap();
    let mut keep: Vec<String> = Vec::new();
    for (split, want) in [("train", train), ("test", 2)] {
        let chosen: Vec<String> = (0..ds.clips().len())
            .filter(|&i| ds.clips()[i].split == split && ds.clips()[i].frames >= 40)
            .step_by(7)
            .filter(|&i| {
                let w = ds.read_window(i, 0, CONTEXT, 1).unwrap();
                let states: Vec<u8> = w.frames.iter().flat_map(heads).map(|h| h[3] as u8).collect();
                states.contains(&(LightState::Red as u8)) && states.contains(&(LightState::Green as u8))
            })
            .take(want)
            .map(|i| ds.clips()[i].id.clone())
            .collect();
        assert_eq!(
            chosen.len(),
            want,
            "the sample's {split} split has clips that see lights"
        );
        keep.extend(chosen);
    }
    let out = dir.join("sample");
    for sub in ["logs", "networks"] {
        std::fs::create_dir_all(out.join(sub)).unwrap();
        for e in std::fs::read_dir(sample.join(sub)).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), out.join(sub).join(e.file_name())).unwrap();
        }
    }
    let mut index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(sample.join("index.json")).unwrap()).unwrap();
    index["clips"]
        .as_array_mut()
        .unwrap()
        .retain(|c| keep.iter().any(|k| c["id"] == k.as_str()));
    std::fs::write(out.join("index.json"), serde_json::to_vec(&index).unwrap()).unwrap();
    out
}

/// Checks that the rows `frames` of every scene of the `umgen generate` output `output` decode to the heads
/// SUMO recorded in those frames of the scene's clip (states exactly, positions within half a bin, at most
/// the modality's 8), and counts the heads compared by state.
fn sumo_heads(
    registry: &ModalityRegistry,
    ds: &Dataset,
    output: &Path,
    frames: std::ops::Range<usize>,
) -> [usize; 4] {
    let tokens = read_json(&output.join("tokens.json"));
    let meta = read_json(&output.join("meta.json"));
    let scenes: Vec<Vec<Vec<u32>>> = serde_json::from_value(tokens["scenes"].clone()).unwrap();
    assert_eq!(scenes.len(), 2);
    let mut compared = [0usize; 4];
    for (s, rows) in scenes.iter().enumerate() {
        let clip = meta["contexts"][s]["clip"].as_str().unwrap();
        let real = ds
            .read_window(ds.find_clip(clip).unwrap(), frames.start, frames.len(), 1)
            .unwrap();
        for (row, want) in rows[frames.clone()].iter().zip(&real.frames) {
            let mut decoded = Frame::default();
            assert_eq!(registry.detokenize(row, &mut decoded).unwrap().malformed, 0);
            let (got, want) = (heads(&decoded), heads(want));
            assert_eq!(got.len(), want.len().min(8), "{clip}");
            for (g, w) in got.iter().zip(&want) {
                assert_eq!(g[3], w[3], "{clip}: decoded state against SUMO's");
                assert!((g[0] - w[0]).abs() <= 0.5 + 1e-4 && (g[1] - w[1]).abs() <= 0.5 + 1e-4);
                compared[g[3] as usize] += 1;
            }
        }
    }
    compared
}

fn catalog() -> ModalityCatalog {
    let mut catalog = umgen::builtin_catalog().unwrap();
    catalog.add(KIND, TrafficLight::factory).unwrap();
    catalog
}

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

#[test]
fn the_plugin_binary_trains_exports_generates_evaluates_and_draws_lights() {
    let tmp = tempfile::tempdir().unwrap();
    let t = |p: &str| tmp.path().join(p).display().to_string();
    let data = sample_subset(tmp.path(), 3);
    let data = data.display().to_string();
    let config = "modalities/traffic-light/configs/tiny-lights.toml";
    let log = lights(&[
        "train",
        "--config",
        config,
        "--set",
        &format!("train.data={data}"),
        "--set",
        &format!("train.out_dir={}", t("run")),
        "--set",
        &format!("train.tokens={}", t("tokens")),
        "--set",
        "train.steps=6",
        "--set",
        "train.checkpoint_every=6",
        // The follow rule brakes the agents for red lights too (`backbone.track_stops`).
        "--set",
        "backbone.track_follow=true",
        "--set",
        "backbone.track_stops=lights",
    ]);
    assert!(log.contains("tokenized"), "{log}");
    lights(&[
        "export",
        "--checkpoint",
        &t("run"),
        "--out",
        &t("bundle"),
        "--golden",
        "2",
    ]);
    // The manifest records the lights' stop slots for every runner's hint.
    let stops = &read_json(&tmp.path().join("bundle/manifest.json"))["backbone"]["track"]["stops"];
    assert_eq!(stops["stop"], serde_json::json!([129]), "{stops}");
    assert_eq!(stops["go"], serde_json::json!([130, 131]), "{stops}");

    // The stock commands' catalog does not know the kind, and says which.
    let err = Bundle::open_with(&tmp.path().join("bundle"), &umgen::builtin_catalog().unwrap())
        .unwrap_err()
        .to_string();
    assert!(err.contains("traffic_light"), "{err}");

    // Two frames after 4 of context, for 2 test clips.
    let generate = |out: &str, extra: &[&str]| {
        let (bundle, contexts) = (t("bundle"), format!("{data}:test:2:{CONTEXT}"));
        let mut args = vec!["generate", "--bundle", &bundle, "--contexts", &contexts];
        args.extend(["--frames", "2"]);
        args.extend(extra);
        let out = t(out);
        args.extend(["--out", out.as_str()]);
        lights(&args);
    };
    generate("gen", &[]);
    // The context rows decode to SUMO's recorded heads: the states exactly, positions within half a bin.
    let (_, registry) = Bundle::open_with(&tmp.path().join("bundle"), &catalog()).unwrap();
    let ds = Dataset::open(Path::new(&data)).unwrap();
    let meta = read_json(&tmp.path().join("gen/meta.json"));
    let compared = sumo_heads(&registry, &ds, &tmp.path().join("gen"), 0..CONTEXT);
    assert!(
        compared[LightState::Red as usize] > 0 && compared[LightState::Green as usize] > 0,
        "{compared:?}"
    );
    // Generated frames carry decoded lights: well-formed heads, at most `count`.
    let generated: Vec<SceneClip> =
        serde_json::from_value(read_json(&tmp.path().join("gen/scenes.json"))).unwrap();
    for f in generated.iter().flat_map(|c| &c.frames) {
        let h = heads(f);
        assert!(
            h.len() <= 8 && h.iter().all(|h| (0.0..=3.0).contains(&h[3])),
            "{h:?}"
        );
    }

    // `--recorded lights`: the generated frames hold SUMO's lights of those frames, so that the agents
    // are drawn given the real lights.
    generate("gen-recorded", &["--recorded", "lights", "--recorded-ego"]);
    let recorded_meta = read_json(&tmp.path().join("gen-recorded/meta.json"));
    assert_eq!(recorded_meta["recorded"], serde_json::json!(["lights", "ego"]));
    let given = sumo_heads(
        &registry,
        &ds,
        &tmp.path().join("gen-recorded"),
        CONTEXT..CONTEXT + 2,
    );
    assert!(given.iter().sum::<usize>() > 0, "no head given");

    // The PyTorch runner moves the agent slots as umgen does, red lights included: the golden logits
    // and greedy frames agree.
    generate("greedy", &["--top-k", "1"]);
    python_runner_check(&tmp.path().join("bundle"), &tmp.path().join("greedy/tokens.json"));

    lights(&[
        "eval",
        "--generated",
        &t("gen"),
        "--reference",
        &data,
        "--split",
        "test",
        "--stride",
        "50",
    ]);
    assert!(tmp.path().join("gen/eval/report.json").exists());
    lights(&["viz", "--generated", &t("gen"), "--out", &t("gen.gif")]);
    assert!(tmp.path().join("gen.gif").exists());

    // `viz --data --config` draws each head's state colour; without a config there are no marks.
    let clip = meta["contexts"][0]["clip"].as_str().unwrap();
    let frame0 = heads(
        &ds.read_window(ds.find_clip(clip).unwrap(), 0, 1, 1)
            .unwrap()
            .frames[0],
    );
    let pixels = |with_config: bool| {
        let dir = t(if with_config { "png-marks" } else { "png-plain" });
        let mut args = vec!["viz", "--data", &data, "--clip", clip, "--frames", "1", "--out"];
        let gif = format!("{dir}.gif");
        args.extend([gif.as_str(), "--png-dir", dir.as_str()]);
        if with_config {
            args.extend(["--config", config]);
        }
        lights(&args);
        let decoder = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(Path::new(&dir).join("frame-0000.png")).unwrap(),
        ));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        buf.chunks(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect::<Vec<[u8; 3]>>()
    };
    let (marked, plain) = (pixels(true), pixels(false));
    for state in [LightState::Red, LightState::Green] {
        let c = colour(state);
        let seen = frame0.iter().any(|h| h[3] as u8 == state as u8);
        let count = |p: &[[u8; 3]]| p.iter().filter(|&&p| p == c).count();
        assert_eq!(
            count(&marked) > 0,
            seen,
            "{state:?} drawn where the frame has such a head"
        );
        assert_eq!(count(&plain), 0, "no marks without the modality");
    }
}
