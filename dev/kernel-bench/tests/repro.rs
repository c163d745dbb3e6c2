//! `umgen-kernel-bench repro` on the CPU: repeated runs of the tiny fixture agree bit for bit (the CPU backend
//! sums in a fixed order, so any difference would be a bug in the training loop's seeding), and bad
//! arguments are refused by name.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{kernel_bench, ok, text};
use umgen_tests::run_fixture::Fixture;

#[test]
fn runs_from_one_seed_agree_bit_for_bit() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("repro", 30).unwrap();
    let cfg = cfg.to_str().unwrap();
    let done = kernel_bench(&[
        "repro",
        "--config",
        cfg,
        "--runs",
        "3",
        "--steps",
        "4",
        "--log-every",
        "2",
    ]);
    let out = text(&done.stdout);
    ok(done);
    assert!(out.contains("3 runs of 4 steps"), "{out}");
    for run in 1..3 {
        let line = out
            .lines()
            .find(|l| l.starts_with(&format!("run {run}:")))
            .unwrap_or_else(|| panic!("no line for run {run}: {out}"));
        assert!(line.ends_with("read-outs agree; weights identical"), "{line}");
    }
    assert!(out.contains("run 0: loss "), "{out}");
}

#[test]
fn bad_arguments_are_refused_by_name() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("refused", 30).unwrap();
    let cfg = cfg.to_str().unwrap();
    for (args, words) in [
        (&["--runs", "1"][..], "--runs 1"),
        (&["--steps", "0"][..], "--steps 0"),
        (&["--log-every", "0"][..], "--log-every 0"),
        (&["--tolerance=-1"][..], "--tolerance -1"),
    ] {
        let mut all = vec!["repro", "--config", cfg];
        all.extend(args);
        let out = kernel_bench(&all);
        assert!(!out.status.success(), "{args:?} was accepted");
        let err = text(&out.stderr);
        assert!(err.contains(words), "{args:?}: {err}");
    }
}
