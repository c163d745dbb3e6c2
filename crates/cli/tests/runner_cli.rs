//! The PyTorch runner (`runners/python`) against umgen on the tiny fixture with every option the manifest
//! can hold on (ego module with its own action, AMA, tracked slots by constant acceleration braking for
//! slower ones ahead): the logits of
//! the bundle's golden file, greedy frames token for token, and a refused unknown setting
//! (`tests/python/check_runner.py`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{ok, python_check, umgen};

use umgen::data::Dataset;
use umgen_tests::run_fixture::Fixture;

#[test]
fn the_python_runner_computes_umgens_logits_and_greedy_frames() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("r", 12).unwrap();
    let text = std::fs::read_to_string(&cfg).unwrap().replace(
        "[backbone]\n",
        "[backbone]\ntrack = \"agent\"\ntrack_accel = true\ntrack_follow = true\nego_last = true\n",
    );
    std::fs::write(&cfg, text).unwrap();
    ok(umgen(&["train", "--config", cfg.to_str().unwrap()]));
    let bundle = fx.dir.path().join("bundle");
    let b = bundle.to_str().unwrap();
    let run = fx.run_dir("r");
    ok(umgen(&[
        "export",
        "--checkpoint",
        run.to_str().unwrap(),
        "--out",
        b,
        "--golden",
        "2",
    ]));
    let manifest = umgen::Bundle::open(&bundle).unwrap().manifest;
    assert!(manifest.files.contains_key(umgen::GOLDEN_FILE));
    let generation = manifest.generation.expect("a generation section");
    assert_eq!(generation["groups"][0]["size"], 11, "agent slots of 11 tokens");
    // Greedy frames from two clips' first two frames.
    let ds = Dataset::open(&fx.data).unwrap();
    let context = |i: usize| format!("{}:{}:2", fx.data.display(), ds.clips()[i].id);
    let out = fx.dir.path().join("greedy");
    let (c0, c1) = (context(0), context(1));
    ok(umgen(&[
        "generate",
        "--bundle",
        b,
        "--context",
        &c0,
        "--context",
        &c1,
        "--frames",
        "4",
        "--top-k",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]));
    let tokens = out.join("tokens.json");
    python_check("check_runner.py", &[bundle.as_os_str(), tokens.as_os_str()]);
}
