//! Layering, typing and error messages of configuration loading.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use serde::Deserialize;
use std::io::Write;
use umgen_config::{ConfigError, RawConfig};

#[derive(Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
struct Train {
    steps: usize,
    lr: f64,
    #[serde(default)]
    tags: Vec<String>,
}

#[derive(Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
struct Run {
    train: Train,
    #[serde(default)]
    name: String,
}

fn file(text: &str) -> tempfile::NamedTempFile {
    let mut f = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
    f.write_all(text.as_bytes()).unwrap();
    f
}

fn env(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

const BASE: &str = "name = \"base\"\n[train]\nsteps = 10\nlr = 0.001\n";

#[test]
fn later_layers_win() {
    let f = file(BASE);
    let raw = RawConfig::load_with_env(
        f.path(),
        env(&[("UMGEN__TRAIN__STEPS", "20"), ("UMGEN_LOG", "x")]),
        &[],
    )
    .unwrap();
    assert_eq!(raw.parse::<Run>().unwrap().train.steps, 20);
    let sets = [
        "train.steps=30".to_string(),
        "train.tags=[\"a\", \"b\"]".into(),
        "name=plain words".into(),
    ];
    let raw = RawConfig::load_with_env(f.path(), env(&[("UMGEN__TRAIN__STEPS", "20")]), &sets).unwrap();
    let run: Run = raw.parse().unwrap();
    assert_eq!(run.train.steps, 30);
    assert_eq!(run.train.tags, vec!["a", "b"]);
    assert_eq!(run.name, "plain words");
    assert_eq!(run.train.lr, 0.001);
    let train: Train = raw.section("train").unwrap();
    assert_eq!(train.steps, 30);
}

#[test]
fn unknown_keys_name_key_and_layer() {
    let f = file(&format!("{BASE}stepz = 3\n"));
    let err = RawConfig::load_with_env(f.path(), env(&[]), &[])
        .unwrap()
        .parse::<Run>()
        .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("`stepz`") && msg.contains(&f.path().display().to_string()),
        "{msg}"
    );

    let f = file(BASE);
    let err = RawConfig::load_with_env(f.path(), env(&[]), &["train.stepz=3".into()])
        .unwrap()
        .parse::<Run>()
        .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("train.stepz") && msg.contains("--set train.stepz=3"),
        "{msg}"
    );

    let err = RawConfig::load_with_env(f.path(), env(&[("UMGEN__TRAIN__LRR", "1")]), &[])
        .unwrap()
        .parse::<Run>()
        .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("train.lrr") && msg.contains("UMGEN__TRAIN__LRR"),
        "{msg}"
    );
}

#[test]
fn wrong_types_name_the_key() {
    let f = file(BASE);
    let raw = RawConfig::load_with_env(f.path(), env(&[]), &["train.steps=many".into()]).unwrap();
    match raw.parse::<Run>().unwrap_err() {
        ConfigError::Key { key, origin, message } => {
            assert_eq!(key, "train.steps");
            assert!(origin.contains("--set"), "{origin}");
            assert!(message.contains("many"), "{message}");
        }
        other => panic!("unexpected {other}"),
    }
    let f = file("[train]\nsteps = -1\nlr = 0.1\n");
    let msg = RawConfig::load_with_env(f.path(), env(&[]), &[])
        .unwrap()
        .parse::<Run>()
        .unwrap_err()
        .to_string();
    assert!(msg.contains("train.steps"), "{msg}");
}

#[test]
fn file_and_override_errors() {
    let missing = std::path::Path::new("/nonexistent/umgen.toml");
    let msg = RawConfig::load_with_env(missing, env(&[]), &[])
        .unwrap_err()
        .to_string();
    assert!(msg.contains("/nonexistent/umgen.toml"), "{msg}");
    let f = file("[train\nsteps = 1\n");
    let msg = RawConfig::load_with_env(f.path(), env(&[]), &[])
        .unwrap_err()
        .to_string();
    assert!(msg.contains("not valid TOML") && msg.contains("line 1"), "{msg}");
    let f = file(BASE);
    for bad in ["train.steps", "=3", "train..steps=3", "tr ain=3"] {
        let msg = RawConfig::load_with_env(f.path(), env(&[]), &[bad.into()])
            .unwrap_err()
            .to_string();
        assert!(msg.contains(&format!("`{bad}`")), "{msg}");
    }
}
