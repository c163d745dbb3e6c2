//! `umgen bench train --alternate`: steps take turns between a kernel setting's values in one process, and
//! settings that would change the run are refused by name.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::PathBuf;
use std::process::{Command, Output};

fn tiny() -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml");
    path.to_str().unwrap().to_string()
}

fn bench(extra: &[&str]) -> Output {
    let tiny = tiny();
    let mut args = vec![
        "bench",
        "train",
        "--config",
        tiny.as_str(),
        "--set",
        "train.batch_size=1",
    ];
    args.extend_from_slice(extra);
    Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(&args)
        .env_remove("UMGEN_LOG")
        .output()
        .unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn alternating_steps_are_timed_per_value() {
    let out = bench(&[
        "--steps",
        "3",
        "--warmup",
        "2",
        "--alternate",
        "train.xent=fused,burn",
    ]);
    let report = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let lines: Vec<&str> = report.lines().filter(|l| l.starts_with("alternate")).collect();
    assert_eq!(lines.len(), 2, "{report}");
    // The warm-up took one turn each (steps 0 and 1); the timed steps 2, 3 and 4 ran fused, burn, fused.
    assert!(
        lines[0].contains("train.xent=fused") && lines[0].contains("median of 2 steps"),
        "{report}"
    );
    assert!(
        lines[1].contains("train.xent=burn") && lines[1].contains("median of 1 steps"),
        "{report}"
    );
    assert!(lines[0].contains("1.000×"), "{report}");
}

#[test]
fn alternation_refuses_what_is_not_a_kernel_choice() {
    let refused = |extra: &[&str]| {
        let out = bench(extra);
        assert_eq!(out.status.code(), Some(1), "{}", text(&out.stdout));
        text(&out.stderr)
    };
    let err = refused(&["--alternate", "train.lr=0.001,0.002"]);
    assert!(
        err.contains("train.lr=0.001") && err.contains("not only a kernel choice"),
        "{err}"
    );
    // tiny.toml computes in f32, so bf16 is the value that changes the model.
    let err = refused(&["--alternate", "backbone.precision=f32,bf16"]);
    assert!(
        err.contains("backbone.precision=bf16") && err.contains("not only a kernel choice"),
        "{err}"
    );
    let err = refused(&["--alternate", "train.xent=fused"]);
    assert!(err.contains("two or more values"), "{err}");
    let err = refused(&["--alternate", "train.xent"]);
    assert!(err.contains("KEY=V1,V2"), "{err}");
    let err = refused(&["--alternate", "train.xent=fused,fast"]);
    assert!(err.contains("train.xent=fast"), "{err}");
    let err = refused(&["--warmup", "1", "--alternate", "train.xent=fused,burn"]);
    assert!(err.contains("--warmup 2"), "{err}");
}
