//! What `umgen train` does with runs that go wrong, on a tiny imported SUMO fixture: a resume that finds
//! no readable checkpoint fails and touches nothing, non-finite steps are skipped and stop the run
//! without a bad checkpoint, bad numbers are refused by key and source before anything is written, and
//! what interrupted saves left is removed.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{ok, safetensors_f32, text, umgen};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use umgen_tests::run_fixture::Fixture;

/// Every file under `dir` with its bytes.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(p.clone(), std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

fn train(cfg: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["train", "--config", cfg.to_str().unwrap()];
    args.extend_from_slice(extra);
    umgen(&args)
}

fn failure(out: &std::process::Output) -> String {
    assert!(!out.status.success(), "accepted: {}", text(&out.stdout));
    text(&out.stderr)
}

#[test]
fn a_resume_without_a_readable_checkpoint_fails_and_changes_nothing() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("r", 5).unwrap();
    ok(train(&cfg, &[]));
    let run = fx.run_dir("r");
    let ckpt = run.join("checkpoints/step-000000005");
    let weights = ckpt.join("model.safetensors");
    let good = std::fs::read(&weights).unwrap();
    let cfg8 = fx.config("r", 8).unwrap();
    let damages: [(&str, &dyn Fn()); 3] = [
        ("truncated", &|| {
            std::fs::write(&weights, &good[..good.len() / 2]).unwrap()
        }),
        ("flipped byte", &|| {
            let mut b = good.clone();
            b[good.len() - 5] ^= 0x10;
            std::fs::write(&weights, b).unwrap();
        }),
        ("no manifest", &|| {
            std::fs::write(&weights, &good).unwrap();
            std::fs::remove_file(ckpt.join("manifest.json")).unwrap();
        }),
    ];
    for (what, damage) in damages {
        damage();
        let before = snapshot(&run);
        let err = failure(&train(&cfg8, &["--resume"]));
        assert!(
            err.contains("none is readable") && err.contains("step-000000005"),
            "{what}: {err}"
        );
        let reason = match what {
            "no manifest" => "no readable manifest",
            _ => "fails its checksum",
        };
        assert!(err.contains(reason), "{what}: {err}");
        assert_eq!(before, snapshot(&run), "{what}: the run directory changed");
    }
}

#[test]
fn non_finite_steps_stop_the_run_without_a_bad_checkpoint() {
    let fx = Fixture::new().unwrap();
    // A learning rate that makes the loss overflow within a few steps; a checkpoint every step.
    let blow_up = [
        "--set",
        "train.lr=1e6",
        "--set",
        "train.grad_clip=0",
        "--set",
        "train.warmup=0",
        "--set",
        "train.checkpoint_every=1",
    ];
    let out = train(
        &fx.config("n", 10).unwrap(),
        &[&blow_up[..], &["--set", "train.max_skipped_steps=2"]].concat(),
    );
    let err = failure(&out);
    let log = text(&out.stdout) + &err;
    // The first non-finite step is named with its loss terms and gradients, and skipped.
    let warned = log
        .lines()
        .find(|l| l.contains("skipped since the last log"))
        .unwrap_or_else(|| panic!("{log}"));
    assert!(
        warned.contains("loss NaN") && warned.contains("oar/agent") && warned.contains("gradient norm NaN"),
        "{warned}"
    );
    assert!(warned.contains("are not finite, the first `"), "{warned}");
    assert!(
        err.contains("not finite") && err.contains("2 steps in a row skipped (steps "),
        "{err}"
    );
    // The step of the first skip, as the log counts steps; checkpoints only from steps before it, all
    // finite, none pruned for a skipped one.
    let first: u64 = warned
        .split("the first at step ")
        .nth(1)
        .unwrap()
        .split(':')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let ckpts = fx.run_dir("n").join("checkpoints");
    let mut steps = Vec::new();
    for e in std::fs::read_dir(&ckpts).unwrap() {
        let dir = e.unwrap().path();
        let name = dir.file_name().unwrap().to_string_lossy().into_owned();
        if let Some(step) = name.strip_prefix("step-") {
            for (tensor, values) in safetensors_f32(&dir.join("model.safetensors")) {
                assert!(values.iter().all(|v| v.is_finite()), "{name}: {tensor}");
            }
            steps.push(step.parse::<u64>().unwrap());
        }
    }
    steps.sort();
    let kept: Vec<u64> = (first.saturating_sub(3).max(1)..first).collect();
    assert_eq!(steps, kept, "{log}");

    // `stop` ends the run at the first such step, naming the policy.
    let out = train(
        &fx.config("s", 10).unwrap(),
        &[&blow_up[..], &["--set", "train.nonfinite=\"stop\""]].concat(),
    );
    let err = failure(&out);
    assert!(
        err.contains(&format!("step {first}:")) && err.contains("train.nonfinite = \"stop\""),
        "{err}"
    );
}

#[test]
fn bad_numbers_are_refused_by_key_and_source_before_anything_is_written() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("v", 5).unwrap();
    for (set, key) in [
        ("train.lr=-1", "train.lr"),
        ("train.lr=nan", "train.lr"),
        ("train.weight_decay=-5", "train.weight_decay"),
        ("train.batch_size=0", "train.batch_size"),
        ("train.beta2=1.0", "train.beta2"),
        ("backbone.dropout=1.5", "backbone.dropout"),
    ] {
        let err = failure(&train(&cfg, &["--set", set]));
        assert!(
            err.contains(&format!("`{key}`")) && err.contains(&format!("from --set {set}")),
            "{set}: {err}"
        );
        assert!(!fx.run_dir("v").exists(), "{set}: the run directory was made");
    }
    // From the environment and from the file.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(["train", "--config", cfg.to_str().unwrap()])
        .env("UMGEN__TRAIN__LR", "-1")
        .output()
        .unwrap();
    let err = failure(&out);
    assert!(
        err.contains("`train.lr`") && err.contains("environment variable UMGEN__TRAIN__LR"),
        "{err}"
    );
    let bad = fx.run_dir("v").with_extension("bad.toml");
    let body = std::fs::read_to_string(&cfg)
        .unwrap()
        .replace("lr = 3e-3", "lr = -3e-3");
    std::fs::write(&bad, body).unwrap();
    let err = failure(&umgen(&["train", "--config", bad.to_str().unwrap()]));
    assert!(
        err.contains("`train.lr`") && err.contains(&format!("in {}", bad.display())),
        "{err}"
    );
    assert!(!fx.run_dir("v").exists());
}

#[test]
fn a_refused_resume_leaves_the_run_directory_and_stale_saves_go() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("m", 5).unwrap();
    ok(train(&cfg, &[]));
    let run = fx.run_dir("m");
    let before = snapshot(&run);
    let err = failure(&train(
        &cfg,
        &[
            "--resume",
            "--set",
            "backbone.d_model=48",
            "--set",
            "backbone.heads=3",
        ],
    ));
    assert!(err.contains("does not match this run"), "{err}");
    assert_eq!(before, snapshot(&run), "the refused run changed its directory");

    // What a killed save left is removed when the next run starts, with a log line.
    let ckpts = run.join("checkpoints");
    let stale = ckpts.join(".step-000000010.tmp-4242");
    std::fs::create_dir_all(&stale).unwrap();
    std::fs::write(stale.join("model.safetensors"), [0u8; 1000]).unwrap();
    std::fs::write(ckpts.join(".latest.tmp-4242"), b"step-000000010").unwrap();
    let log = ok(train(&fx.config("m", 7).unwrap(), &["--resume"]));
    assert!(
        log.contains(".step-000000010.tmp-4242 (1000 bytes)") && log.contains(".latest.tmp-4242"),
        "{log}"
    );
    assert!(!stale.exists() && !ckpts.join(".latest.tmp-4242").exists());
    assert!(ckpts.join("step-000000007").exists());
}

/// Sets the last value of the last tensor of safetensors file `path` to NaN and returns the file's new
/// SHA-256 and size, for a manifest to list.
fn poison(path: &Path) -> (String, u64) {
    let mut bytes = std::fs::read(path).unwrap();
    let n = bytes.len();
    bytes[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(path, &bytes).unwrap();
    (umgen::checkpoint::sha256(&bytes), n as u64)
}

/// Lists `file`'s new checksum and size in the manifest at `manifest` (under `files`).
fn relist(manifest: &Path, file: &str, (sha, bytes): (String, u64)) {
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(manifest).unwrap()).unwrap();
    m["files"][file]["sha256"] = sha.into();
    m["files"][file]["bytes"] = bytes.into();
    std::fs::write(manifest, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

#[test]
fn control_entries_that_cannot_apply_and_non_finite_weights_are_refused() {
    let fx = Fixture::new().unwrap();
    ok(train(&fx.config("g", 5).unwrap(), &[]));
    let run = fx.run_dir("g");
    let bundle = fx.dir.path().join("bundle");
    let export = |from: &Path, to: &Path| {
        umgen(&[
            "export",
            "--checkpoint",
            from.to_str().unwrap(),
            "--out",
            to.to_str().unwrap(),
        ])
    };
    ok(export(&run, &bundle));
    let ds = umgen::data::Dataset::open(&fx.data).unwrap();
    let context = format!("{}:{}:2", fx.data.display(), ds.clips()[0].id);
    let generate = |bundle: &Path, control: &Path, extra: &[&str]| {
        let out = fx.dir.path().join("gen");
        let mut args = vec![
            "generate",
            "--bundle",
            bundle.to_str().unwrap(),
            "--context",
            &context,
            "--frames",
            "2",
            "--control",
            control.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        umgen(&args)
    };
    let beyond = fx.dir.path().join("beyond.toml");
    std::fs::write(&beyond, "[[ego]]\nfrom = 50\nto = 60\ndx = 2.0\n").unwrap();
    let err = failure(&generate(&bundle, &beyond, &[]));
    assert!(
        err.contains(&beyond.display().to_string())
            && err.contains("ego[0] (frames 50 to 60) starts after the last generated frame, 1")
            && err.contains("--allow-partial-control"),
        "{err}"
    );
    let log = ok(generate(&bundle, &beyond, &["--allow-partial-control"]));
    assert!(
        log.contains("ego[0] (frames 50 to 60)") && log.contains("generating without it"),
        "{log}"
    );
    let slot = fx.dir.path().join("slot.toml");
    std::fs::write(&slot, "[[agent]]\nslot = 99\nfrom = 0\nto = 1\nx = 5.0\n").unwrap();
    let err = failure(&generate(&bundle, &slot, &[]));
    assert!(
        err.contains("agent[0].slot = 99: this model has slots 0 to "),
        "{err}"
    );

    // A checkpoint with a NaN weight is not exported, and a bundle with one is not generated from.
    let newest = run.join("checkpoints/step-000000005");
    relist(
        &newest.join("manifest.json"),
        "model.safetensors",
        poison(&newest.join("model.safetensors")),
    );
    let err = failure(&export(&run, &fx.dir.path().join("nan-bundle")));
    assert!(
        err.contains("not finite") && err.contains("export an earlier checkpoint"),
        "{err}"
    );
    assert!(!fx.dir.path().join("nan-bundle").exists());
    relist(
        &bundle.join("manifest.json"),
        "model.safetensors",
        poison(&bundle.join("model.safetensors")),
    );
    let err = failure(&generate(&bundle, &beyond, &["--allow-partial-control"]));
    assert!(
        err.contains("model.safetensors") && err.contains("not finite"),
        "{err}"
    );
}
