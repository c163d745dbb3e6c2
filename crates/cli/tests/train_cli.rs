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
    metric_lines(run)
        .iter()
        .filter_map(|v| Some((v["step"].as_u64()?, v["loss"].as_f64()?)))
        .collect()
}

/// Every line of `metrics.jsonl`: the training losses' and the validation losses' (`val/…`).
fn metric_lines(run: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    text.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

#[test]
fn validation_logs_held_out_losses_and_leaves_training_alone() {
    let fx = Fixture::new().unwrap();
    let plain = fx.config("plain", 6).unwrap();
    ok(umgen(&["train", "--config", plain.to_str().unwrap()]));
    let with = fx.config("val", 6).unwrap();
    let val_args = |every: &'static str| {
        [
            "--set",
            every,
            "--set",
            "train.val_split=\"train\"",
            "--set",
            "train.val_windows=3",
        ]
    };
    let mut args = vec!["train", "--config", with.to_str().unwrap()];
    args.extend(val_args("train.val_every=4"));
    let log = ok(umgen(&args));
    // Every 4 steps and after the last: steps 4 and 6, each with the total and its parts.
    let val: Vec<serde_json::Value> = metric_lines(&fx.run_dir("val"))
        .into_iter()
        .filter(|v| v.get("val/loss").is_some())
        .collect();
    let steps: Vec<u64> = val.iter().map(|v| v["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [4, 6], "{val:?}");
    for v in &val {
        let at = |k: &str| v[k].as_f64().unwrap();
        // The total is OAR + TAR + ego_loss_weight (1) · ego, as in training.
        let sum = at("val/oar") + at("val/tar") + at("val/ego");
        assert!((sum - at("val/loss")).abs() < 1e-4 * at("val/loss"), "{v}");
        assert!(at("val/loss").is_finite() && at("val/loss") > 0.0, "{v}");
    }
    assert!(
        log.contains("val/loss") && log.contains("3 windows of split `train`"),
        "{log}"
    );
    // Validation reads the weights and changes nothing: the same losses and final weights as without it.
    assert_eq!(losses(&fx.run_dir("plain")), losses(&fx.run_dir("val")));
    let weights = |run: &str| {
        std::fs::read(
            fx.run_dir(run)
                .join("checkpoints/step-000000006/model.safetensors"),
        )
        .unwrap()
    };
    assert!(weights("plain") == weights("val"), "the final weights differ");
    // Nor does it belong to the run's identity: a run resumes under other validation settings.
    let longer = fx.config("val", 8).unwrap();
    let mut args = vec!["train", "--config", longer.to_str().unwrap(), "--resume"];
    args.extend(val_args("train.val_every=1"));
    ok(umgen(&args));
    // A split without windows is refused by name before any step.
    let mut args = vec![
        "train",
        "--config",
        plain.to_str().unwrap(),
        "--resume",
        "--set",
        "train.val_every=2",
    ];
    args.extend(["--set", "train.val_split=\"nowhere\""]);
    let refused = umgen(&args);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && err.contains("train.val_split = \"nowhere\""),
        "{err}"
    );
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
