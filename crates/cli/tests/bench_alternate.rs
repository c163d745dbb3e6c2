//! `umgen bench train --alternate`: steps take turns between a kernel setting's values in one process, and
//! settings that would change the run are refused by name; the train and all-reduce benches refuse to
//! time nothing.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::text;

use std::path::PathBuf;
use std::process::Output;

/// `umgen bench train` on the tiny config, one window a step, with `extra` arguments.
fn bench(extra: &[&str]) -> Output {
    let tiny = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml");
    let mut args = vec![
        "bench",
        "train",
        "--config",
        tiny.to_str().unwrap(),
        "--set",
        "train.batch_size=1",
    ];
    args.extend_from_slice(extra);
    common::umgen(&args)
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
fn the_kernels_stream_alternates() {
    let out = bench(&[
        "--steps",
        "2",
        "--warmup",
        "2",
        "--alternate",
        "train.kernel_stream=cubecl,side",
    ]);
    let report = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        report.contains("train.kernel_stream=cubecl") && report.contains("train.kernel_stream=side"),
        "{report}"
    );
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

#[test]
fn benches_without_a_timed_run_are_refused() {
    // Without a timed step there is no median to print (both panicked on an empty list before).
    let out = bench(&["--steps", "0"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("--steps 0"), "{}", text(&out.stderr));
    let out = common::umgen(&["bench", "allreduce", "--iters", "0"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("--iters 0"), "{}", text(&out.stderr));
}
