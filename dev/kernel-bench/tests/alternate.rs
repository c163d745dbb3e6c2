//! `umgen-kernel-bench train --alternate`: steps take turns between a kernel setting's values in one
//! process, and settings that would change the run are refused by name.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::text;

use std::path::PathBuf;
use std::process::Output;

/// `umgen-kernel-bench train` on the tiny config, one window a step, with `extra` arguments.
fn bench(extra: &[&str]) -> Output {
    let tiny = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml");
    let mut args = vec![
        "train",
        "--config",
        tiny.to_str().unwrap(),
        "--set",
        "train.batch_size=1",
    ];
    args.extend_from_slice(extra);
    common::kernel_bench(&args)
}

/// The report of five steps (two warm-up, three timed) alternating as `spec` says; the run must succeed.
fn alternated(spec: &str) -> String {
    let out = bench(&["--steps", "3", "--warmup", "2", "--alternate", spec]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    text(&out.stdout)
}

/// The report's `alternate` lines, checked to name `key`'s two values in turn: the warm-up took one turn
/// each (steps 0 and 1), the timed steps 2, 3 and 4 ran the first, the second, the first.
fn check_turns(report: &str, key: &str, [first, second]: [&str; 2]) {
    let lines: Vec<&str> = report.lines().filter(|l| l.starts_with("alternate")).collect();
    assert_eq!(lines.len(), 2, "{report}");
    assert!(
        lines[0].contains(&format!("{key}={first}")) && lines[0].contains("median of 2 steps"),
        "{report}"
    );
    assert!(
        lines[1].contains(&format!("{key}={second}")) && lines[1].contains("median of 1 steps"),
        "{report}"
    );
    assert!(lines[0].contains("1.000×"), "{report}");
}

#[test]
fn alternating_steps_are_timed_per_value() {
    let report = alternated("train.kernels.xent=fused,burn");
    check_turns(&report, "train.kernels.xent", ["fused", "burn"]);
    // The stream umgen's CUDA kernels run on is a kernel choice too (the CPU runs neither).
    let report = alternated("train.kernels.stream=cubecl,side");
    check_turns(&report, "train.kernels.stream", ["cubecl", "side"]);
    // And what steps AdamW (a resumed run may switch it: it keeps the run's identity).
    let report = alternated("train.kernels.adamw=burn,fused");
    check_turns(&report, "train.kernels.adamw", ["burn", "fused"]);
    // And which thread launches the custom operations.
    let report = alternated("train.kernels.launch_thread=caller,device");
    check_turns(&report, "train.kernels.launch_thread", ["caller", "device"]);
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
    let err = refused(&["--alternate", "train.kernels.xent=fused"]);
    assert!(err.contains("two or more values"), "{err}");
    let err = refused(&["--alternate", "train.kernels.xent"]);
    assert!(err.contains("KEY=V1,V2"), "{err}");
    let err = refused(&["--alternate", "train.kernels.xent=fused,fast"]);
    assert!(err.contains("train.kernels.xent=fast"), "{err}");
    let err = refused(&["--warmup", "1", "--alternate", "train.kernels.xent=fused,burn"]);
    assert!(err.contains("--warmup 2"), "{err}");
}
