//! The `umgen` binary end to end: output, exit codes and error messages.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::text;

use std::path::PathBuf;
use std::process::{Command, Output};

fn config(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs")
        .join(name)
}

fn umgen(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(args)
        .env_remove("UMGEN_LOG")
        .output()
        .unwrap()
}

/// Runs a command that must fail cleanly and returns its stderr.
fn failure(args: &[&str], envs: &[(&str, &str)]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(args)
        .envs(envs.iter().copied())
        .output()
        .unwrap();
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "stderr: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(err.starts_with("error: "), "{err}");
    err
}

#[test]
fn layout_of_the_paper_config() {
    let out = umgen(&["layout", "--config", config("paper.toml").to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let table = text(&out.stdout);
    assert!(table.contains("N = 2251 tokens per frame"), "{table}");
    // modality, kind, start, offset, tokens, end, vocab
    let rows: Vec<Vec<String>> = table
        .lines()
        .filter(|l| {
            ["ego ", "map ", "agent ", "image "]
                .iter()
                .any(|m| l.starts_with(m))
        })
        .map(|l| l.split_whitespace().map(String::from).collect())
        .collect();
    let expect = [
        ["ego", "ego", "0", "1", "3", "4", "1024"],
        ["map", "map", "5", "6", "1024", "1030", "8192"],
        ["agent", "agent", "1031", "1032", "704", "1736", "1028"],
        ["image", "image", "1737", "1738", "512", "2250", "8192"],
    ];
    assert_eq!(rows.len(), 4, "{table}");
    for (row, want) in rows.iter().zip(expect) {
        assert_eq!(&row[..7], &want[..], "{table}");
    }
}

#[test]
fn layout_as_json_with_overrides() {
    let path = config("paper.toml");
    let args = [
        "layout",
        "--json",
        "--config",
        path.to_str().unwrap(),
        "--set",
        "layout.boundary_tokens=false",
        "--set",
        "modality.agent.max_agents=60",
    ];
    let out = umgen(&args);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // The PyTorch reference's layout: 3 + 1024 + 660 + 512.
    assert_eq!(v["tokens_per_frame"], 2199);
    assert_eq!(v["segments"][2]["offset"], 1027);
    assert_eq!(v["segments"][2]["tokens"], 660);
    assert_eq!(v["fingerprint"].as_str().unwrap().len(), 64);
}

#[test]
fn config_errors_name_the_key_and_fail() {
    let paper = config("paper.toml");
    let p = paper.to_str().unwrap();
    let err = failure(
        &["layout", "--config", p, "--set", "modality.agent.max_agent=3"],
        &[],
    );
    assert!(
        err.contains("`modality.agent.max_agent`") && err.contains("unknown field"),
        "{err}"
    );
    let err = failure(
        &["layout", "--config", p, "--set", "layout.boundary_tokens=maybe"],
        &[],
    );
    assert!(
        err.contains("`layout.boundary_tokens`") && err.contains("expected a boolean"),
        "{err}"
    );
    let err = failure(&["layout", "--config", p, "--set", "modality.map.grid=[32]"], &[]);
    assert!(err.contains("`modality.map.grid`"), "{err}");
    let err = failure(&["layout", "--config", p], &[("UMGEN__LAYOUT__ORDER", "ego")]);
    assert!(
        err.contains("`layout.order`") && err.contains("UMGEN__LAYOUT__ORDER"),
        "{err}"
    );
    let err = failure(
        &[
            "layout",
            "--config",
            p,
            "--set",
            "layout.order=[\"ego\", \"map\", \"agent\", \"image\", \"map\"]",
        ],
        &[],
    );
    assert!(err.contains("duplicate modality name `map`"), "{err}");
    // Only a modality of tracked slots can be moved as one.
    let err = failure(&["layout", "--config", p, "--set", "backbone.track=\"map\""], &[]);
    assert!(
        err.contains("backbone.track") && err.contains("`map` does not declare slots"),
        "{err}"
    );
    let off = [
        "--set",
        "backbone.track=\"\"",
        "--set",
        "backbone.track_accel=true",
    ];
    let err = failure(&[&["layout", "--config", p][..], &off].concat(), &[]);
    assert!(
        err.contains("backbone.track_accel") && err.contains("needs `backbone.track`"),
        "{err}"
    );
    let follow = [
        "--set",
        "backbone.track=\"\"",
        "--set",
        "backbone.track_accel=false",
        "--set",
        "backbone.track_follow=true",
    ];
    let err = failure(&[&["layout", "--config", p][..], &follow].concat(), &[]);
    assert!(
        err.contains("backbone.track_follow") && err.contains("needs `backbone.track`"),
        "{err}"
    );
    // Stop points are braked for by the follow rule, and only a modality that declares them has them.
    let stops = [
        "--set",
        "backbone.track=agent",
        "--set",
        "backbone.track_stops=agent",
    ];
    let err = failure(&[&["layout", "--config", p][..], &stops].concat(), &[]);
    assert!(
        err.contains("backbone.track_stops") && err.contains("backbone.track_follow = true"),
        "{err}"
    );
    let with_follow = ["--set", "backbone.track_follow=true"];
    let err = failure(
        &[&["layout", "--config", p][..], &stops, &with_follow].concat(),
        &[],
    );
    assert!(
        err.contains("backbone.track_stops") && err.contains("`agent` does not declare slots of stop points"),
        "{err}"
    );
    let err = failure(&["layout", "--config", "/no/such/config.toml"], &[]);
    assert!(err.contains("/no/such/config.toml"), "{err}");
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[layout]\norder = [\"ego\"]\nordr = 1\n").unwrap();
    let err = failure(&["layout", "--config", bad.to_str().unwrap()], &[]);
    assert!(err.contains("`layout.ordr`") && err.contains("bad.toml"), "{err}");
    // A tokenize device list is split and a bad device named.
    let tiny = config("tiny.toml");
    let out = dir.path().join("tokens");
    let err = failure(
        &[
            "tokenize",
            "--config",
            tiny.to_str().unwrap(),
            "--data",
            "no-data",
            "--out",
            out.to_str().unwrap(),
            "--device",
            "gpu7,cpu",
        ],
        &[],
    );
    assert!(err.contains("device `gpu7`"), "{err}");
}

#[test]
fn version_help_and_doctor() {
    let out = umgen(&["--version"]);
    assert_eq!(
        text(&out.stdout).trim(),
        format!("umgen {}", env!("CARGO_PKG_VERSION"))
    );
    let help = text(&umgen(&["--help"]).stdout);
    assert!(help.contains("layout") && help.contains("doctor"), "{help}");
    // Without the `cuda` feature the doctor only reports that GPU support is not built in.
    if cfg!(not(feature = "cuda")) {
        let out = umgen(&["doctor"]);
        assert!(out.status.success());
        assert!(text(&out.stdout).contains("cuda     not built in"));
    }
}

/// The rows of a `bench generate` table whose first column is one of `keys`, split in columns.
fn table_rows<'a>(table: &'a str, keys: &[&str]) -> Vec<Vec<&'a str>> {
    table
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .filter(|c| c.first().is_some_and(|w| keys.contains(w)) && c.len() >= 7)
        .collect()
}

#[test]
fn bench_generate_engine_prints_a_row_per_batch_and_history_and_agrees_with_burn() {
    let tiny = config("tiny.toml");
    let out = umgen(&[
        "bench",
        "generate",
        "--config",
        tiny.to_str().unwrap(),
        "--history",
        "1,2",
        "--batch",
        "1,2",
        "--frames",
        "1",
        "--check",
        "2",
        "--rollout",
        "2",
        "--profile",
    ]);
    let table = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    // Greedy frames of the engine and of the burn decoder: both f32 on the CPU, the same tokens.
    assert!(
        table.contains("342 of 342 tokens and 2 of 2 frames agree"),
        "{table}"
    );
    let rows = table_rows(&table, &["1", "2"]);
    let keys: Vec<(&str, &str)> = rows.iter().map(|c| (c[0], c[1])).collect();
    assert_eq!(keys, [("1", "1"), ("1", "2"), ("2", "1"), ("2", "2")], "{table}");
    for c in &rows {
        let num = |i: usize| c[i].parse::<f64>().unwrap();
        let (batch, frame_s, ms, fps) = (num(0), num(3), num(4), num(7));
        assert!(
            num(2) > 0.0 && frame_s > 0.0 && num(5) > 0.0 && num(6) > 0.0,
            "{table}"
        );
        // ms/token is the frame over N = 171 tokens, frames/s the batch's scenes over the frame; the
        // frame column is printed to 1 ms, so `want` carries that rounding.
        let tol = 0.0005 / frame_s + 0.002;
        assert!((ms - 1e3 * frame_s / 171.0).abs() <= tol * ms + 1e-4, "{table}");
        assert!((fps - batch / frame_s).abs() <= tol * fps + 0.01, "{table}");
    }
    // The profile lists the window's operations and the step's, each total the sum of its lines.
    for (title, unit) in [("window pass", "ms"), ("decoding step", "µs")] {
        let head = table.lines().position(|l| l.starts_with(title)).expect(title);
        // The number before the unit, in a title or in an operation's line.
        let number = |l: &str| -> f64 {
            let w: Vec<&str> = l.split_whitespace().collect();
            let at = w.iter().position(|&x| x == unit).expect(unit);
            w[at - 1].parse().unwrap()
        };
        let lines: Vec<&str> = table.lines().collect();
        let total = number(lines[head].rsplit(": ").next().unwrap());
        let parts: Vec<f64> = lines[head + 1..]
            .iter()
            .take_while(|l| l.starts_with("  "))
            .filter(|l| !l.ends_with("(not in the step)"))
            .map(|l| number(l))
            .collect();
        assert!(!parts.is_empty() && parts.iter().all(|&p| p >= 0.0), "{table}");
        // Each line is rounded to 0.005, the total to 0.05.
        let sum: f64 = parts.iter().sum();
        let tol = 0.05 + 0.005 * parts.len() as f64;
        assert!((sum - total).abs() <= tol, "{title}: {sum} vs {total}\n{table}");
    }
    assert!(
        table.contains("rollout  2 frames × 1 scene(s) from T = 1"),
        "{table}"
    );
    let err = failure(
        &[
            "bench",
            "generate",
            "--config",
            tiny.to_str().unwrap(),
            "--history",
            "9",
        ],
        &[],
    );
    assert!(
        err.contains("--history 9") && err.contains("backbone.max_frames"),
        "{err}"
    );
}

#[test]
fn bench_generate_burn_decoder_prints_a_row_per_history() {
    let tiny = config("tiny.toml");
    let out = umgen(&[
        "bench",
        "generate",
        "--decoder",
        "burn",
        "--config",
        tiny.to_str().unwrap(),
        "--history",
        "1,3",
        "--tokens",
        "4",
        "--frames",
        "2",
    ]);
    let table = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let rows = table_rows(&table, &["1", "3"]);
    assert_eq!(rows.len(), 2, "{table}");
    for cols in rows {
        assert!(
            cols[1].parse::<f64>().unwrap() > 0.0 && cols[3].parse::<f64>().unwrap() > 0.0,
            "{cols:?}"
        );
        // Frames per second of the batch (1 scene) is 1000 / (ms/token × N), N = 171 for tiny. The table
        // prints ms/token to 3 decimals, so `want` carries that rounding (0.0005 ms, 0.24 % of 0.212 ms)
        // besides the frames/s column's own.
        let fps = cols[6].parse::<f64>().unwrap();
        let ms = cols[1].parse::<f64>().unwrap();
        let want = 1e3 / (ms * 171.0);
        assert!(
            (fps - want).abs() <= (0.0005 / ms + 0.002) * want + 0.001,
            "{cols:?}"
        );
    }
}

#[test]
fn bench_train_preset_names_the_config_it_reads_and_flags_are_checked() {
    let dir = std::env::temp_dir().join(format!("umgen-preset-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(["bench", "train", "--preset", "small"])
        .current_dir(&dir)
        .output()
        .unwrap();
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("configs/small.toml") && err.contains("--config"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
    // The bench takes the trainer's loss options and refuses what the trainer refuses, by key.
    let tiny = config("tiny.toml");
    let err = failure(
        &[
            "bench",
            "train",
            "--config",
            tiny.to_str().unwrap(),
            "--set",
            "train.ordinal_sigma=-2",
        ],
        &[],
    );
    assert!(
        err.contains("`train.ordinal_sigma` (from --set train.ordinal_sigma=-2): -2 must be"),
        "{err}"
    );
    // Neither a config nor a preset, and a time limit that is not a positive number: usage errors.
    let out = umgen(&["bench", "train"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("--config"), "{}", text(&out.stderr));
    let out = umgen(&[
        "tokenizer",
        "train",
        "--config",
        "x.toml",
        "--modality",
        "map",
        "--data",
        "d",
        "--time-limit",
        "0",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("not a positive number of minutes"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn bench_train_times_the_phases_of_the_step() {
    let tiny = config("tiny.toml");
    let out = umgen(&[
        "bench",
        "train",
        "--config",
        tiny.to_str().unwrap(),
        "--steps",
        "1",
        "--warmup",
        "0",
        "--phases",
        "--set",
        "train.batch_size=1",
    ]);
    let report = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let line = report
        .lines()
        .find(|l| l.starts_with("phases"))
        .unwrap_or_else(|| panic!("no phases line: {report}"));
    let ms: Vec<f64> = line
        .split_whitespace()
        .filter_map(|w| w.parse::<f64>().ok())
        .collect();
    assert_eq!(ms.len(), 4, "{line}");
    assert!(
        ms[0] > 0.0 && ms[1] > 0.0,
        "forward and backward take time: {line}"
    );
    // The first step is reported apart: its total and its four phases, which add up to it.
    let line = report
        .lines()
        .find(|l| l.starts_with("first step"))
        .unwrap_or_else(|| panic!("no first-step line: {report}"));
    let s: Vec<f64> = line
        .replace(['(', ')', ',', ':'], " ")
        .split_whitespace()
        .filter_map(|w| w.parse::<f64>().ok())
        .collect();
    assert_eq!(s.len(), 5, "{line}");
    assert!(s[1] > 0.0 && s[2] > 0.0, "{line}");
    assert!((s[0] - s[1..].iter().sum::<f64>()).abs() <= 0.25, "{line}");
}

#[test]
fn benches_without_a_timed_run_are_refused() {
    // Without a timed step there is no median to print.
    let tiny = config("tiny.toml");
    let out = umgen(&[
        "bench",
        "train",
        "--config",
        tiny.to_str().unwrap(),
        "--steps",
        "0",
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("--steps 0"), "{}", text(&out.stderr));
    let out = umgen(&["bench", "allreduce", "--iters", "0"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("--iters 0"), "{}", text(&out.stderr));
}
