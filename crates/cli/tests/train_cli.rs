//! `umgen train` end to end on a tiny imported SUMO fixture: the loss falls, a run killed with SIGKILL and
//! resumed repeats the uninterrupted run's losses exactly, a time limit stops with a checkpoint, damaged
//! checkpoints fall back, other configs are refused, and TensorBoard reads the event files.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{ok, python_check, umgen};

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};
use umgen_tests::run_fixture::Fixture;

/// Loss per step from `metrics.jsonl` (the last line of a step wins: a resumed run repeats steps after its
/// checkpoint).
fn losses(run: &Path) -> BTreeMap<u64, f64> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    text.lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| (v["step"].as_u64().unwrap(), v["loss"].as_f64().unwrap()))
        .collect()
}

#[test]
fn training_learns_survives_sigkill_and_resumes_exactly() {
    let fx = Fixture::new().unwrap();
    // The uninterrupted run.
    let cfg_a = fx.config("a", 30).unwrap();
    let log = ok(umgen(&["train", "--config", cfg_a.to_str().unwrap()]));
    assert!(log.contains("tokenized"), "the first run tokenizes: {log}");
    let a = losses(&fx.run_dir("a"));
    assert_eq!(a.len(), 30);
    let first = a[&1];
    let last: f64 = (26..=30).map(|s| a[&s]).sum::<f64>() / 5.0;
    assert!(last < 0.75 * first, "the loss falls: {first} → {last}");

    // The same run, killed with SIGKILL once a checkpoint exists, then resumed.
    let cfg_b = fx.config("b", 30).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(["train", "--config", cfg_b.to_str().unwrap()])
        .env("NO_COLOR", "1")
        .spawn()
        .unwrap();
    let ckpt = fx.run_dir("b").join("checkpoints/step-000000010");
    let t0 = Instant::now();
    while !ckpt.exists() {
        assert!(t0.elapsed() < Duration::from_secs(120), "no checkpoint appeared");
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert!(!status.success(), "the run was killed before finishing");
    let refused = umgen(&["train", "--config", cfg_b.to_str().unwrap()]);
    assert!(!refused.status.success() && String::from_utf8_lossy(&refused.stderr).contains("--resume"));
    ok(umgen(&["train", "--config", cfg_b.to_str().unwrap(), "--resume"]));
    let b = losses(&fx.run_dir("b"));
    assert_eq!(
        a, b,
        "the resumed run's losses equal the uninterrupted run's, step by step"
    );

    // A time limit stops at the next logging step (every step here) with a checkpoint to resume from.
    let cfg_c = fx.config("c", 30).unwrap();
    let log = ok(umgen(&[
        "train",
        "--config",
        cfg_c.to_str().unwrap(),
        "--time-limit",
        "1e-6",
    ]));
    assert!(log.contains("time limit reached at step 1"), "{log}");
    assert!(fx.run_dir("c").join("checkpoints/step-000000001").exists());
    assert_eq!(losses(&fx.run_dir("c")), BTreeMap::from([(1, a[&1])]));

    // A damaged newest checkpoint is detected and the previous one is used.
    let newest = fx.run_dir("b").join("checkpoints/step-000000030");
    let w = newest.join("model.safetensors");
    let mut bytes = std::fs::read(&w).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x55;
    std::fs::write(&w, bytes).unwrap();
    let cfg_b35 = fx.config("b", 35).unwrap();
    let log = ok(umgen(&[
        "train",
        "--config",
        cfg_b35.to_str().unwrap(),
        "--resume",
    ]));
    assert!(
        log.contains("passing over a damaged checkpoint")
            && log.contains("checksum")
            && log.contains("step 25")
            && log.contains("step-000000030.damaged"),
        "{log}"
    );

    // Resuming run b with overrides that must be refused: the failure's log.
    let refused = |sets: &[&str]| {
        let mut args = vec!["train", "--config", cfg_b35.to_str().unwrap(), "--resume"];
        for kv in sets {
            args.extend(["--set", kv]);
        }
        let out = umgen(&args);
        assert!(!out.status.success(), "{sets:?} was accepted");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    // Another model refuses the checkpoints and names the difference.
    let err = refused(&["backbone.d_model=48", "backbone.heads=3"]);
    assert!(
        err.contains("does not match this run") && err.contains("backbone (d_model, heads)"),
        "{err}"
    );
    // A non-positive AdamW ε is refused by name, before any checkpoint is touched.
    let err = refused(&["train.eps=0"]);
    assert!(err.contains("`train.eps` (from --set train.eps=0)"), "{err}");
    let err = refused(&["train.prior_drop=1.5"]);
    assert!(
        err.contains("`train.prior_drop` (from --set train.prior_drop=1.5): 1.5 must be"),
        "{err}"
    );
    let err = refused(&["train.ordinal_sigma=-1"]);
    assert!(
        err.contains("`train.ordinal_sigma` (from --set train.ordinal_sigma=-1): -1 must be"),
        "{err}"
    );
    // Slots moved by a time the windows do not step (the sample's frames are 0.5 s apart).
    let err = refused(&["backbone.track=\"agent\"", "backbone.step_s=0.25"]);
    assert!(
        err.contains("backbone.step_s = 0.25") && err.contains("windows step 0.5 s"),
        "{err}"
    );

    // TensorBoard's own reader loads the scalars (CI sets UMGEN_TB_PYTHON to a Python with tensorboard).
    let tb = fx.run_dir("a").join("tb");
    python_check(
        "check_tensorboard.py",
        &[tb.as_os_str(), "loss".as_ref(), "30".as_ref()],
    );
}
