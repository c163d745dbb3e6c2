//! `umgen launch` on the CPU: 2 and 3 ranks over TCP end with the parameters of one rank training on the
//! same global batch (the backbone, and a VQ tokenizer with its moving-average codebook); ranks that
//! shard the optimizer state end with the unsharded run's weights; a killed or stopped rank makes the
//! launcher fail within the timeout.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{free_port, largest_difference, launch_args, safetensors_f32, umgen};

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};
use umgen_tests::fixtures::tiny_dataset;

/// Ego and agents only (no VQ tokenizers to train), no dropout (ranks draw different masks).
fn config(dir: &Path, data: &Path, out: &str, steps: u64, batch: usize) -> PathBuf {
    config_with(dir, data, out, steps, batch, 1, false)
}

/// `linear`: AdamW with ε = 1 (and a learning rate to match), whose update is linear in the gradient (a
/// momentum SGD), so that rounding differences between ways of summing the same gradient stay
/// rounding-sized. With the usual ε = 1e-8 the first steps are close to sign descent, and a parameter
/// whose gradient is rounding noise moves by ±lr depending on the summation order.
#[allow(clippy::too_many_arguments)]
fn config_with(
    dir: &Path,
    data: &Path,
    out: &str,
    steps: u64,
    batch: usize,
    accum: usize,
    linear: bool,
) -> PathBuf {
    let (lr, eps) = if linear { (0.3, 1.0) } else { (3e-3, 1e-8) };
    let text = format!(
        "[layout]\norder = [\"ego\", \"agent\"]\n[modality.agent]\nmax_agents = 4\n\
         [backbone]\nalign = \"\"\nd_model = 32\nheads = 2\nmlp_ratio = 2\ndropout = 0.0\nego_hist_layers = 1\nego_env_layers = 1\ntar_layers = 1\noar_layers = 1\nmax_frames = 4\n\
         [train]\nout_dir = \"{}\"\ntokens = \"{}\"\ndata = \"{}\"\nsteps = {steps}\nbatch_size = {batch}\ngrad_accum = {accum}\neps = {eps:e}\nframes = 2\nlr = {lr:e}\nwarmup = 2\nlog_every = 1\ncheckpoint_every = 2\nbucket_mib = 0.01\n",
        dir.join(out).display(),
        dir.join("tokens").display(),
        data.display()
    );
    let p = dir.join(format!("{out}.toml"));
    std::fs::write(&p, text).unwrap();
    p
}

/// Every tensor of the newest checkpoint's weights.
fn weights(run: &Path) -> BTreeMap<String, Vec<f32>> {
    let latest = std::fs::read_to_string(run.join("checkpoints/latest")).unwrap();
    safetensors_f32(
        &run.join("checkpoints")
            .join(latest.trim())
            .join("model.safetensors"),
    )
}

#[test]
fn ranks_over_tcp_match_one_rank_on_the_same_global_batch() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 40).unwrap();
    let one = config_with(dir.path(), &data, "one", 4, 6, 1, true);
    let out = umgen(&["train", "--config", one.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let reference = weights(&dir.path().join("one"));
    let largest_difference = |got: &BTreeMap<String, Vec<f32>>| largest_difference(got, &reference);
    // The yardstick: one rank on half the batch (other data) ends far from the reference.
    let half = config_with(dir.path(), &data, "half", 4, 3, 1, true);
    assert!(
        umgen(&["train", "--config", half.to_str().unwrap()])
            .status
            .success()
    );
    let other_data = largest_difference(&weights(&dir.path().join("half")));
    assert!(other_data > 1e-5, "{other_data}");
    // (ranks, windows per micro-batch, micro-batches per step): always 6 windows per step.
    for (world, batch, accum) in [(2, 3, 1), (3, 2, 1), (2, 1, 3)] {
        let name = format!("ranks{world}-accum{accum}");
        let cfg = config_with(dir.path(), &data, &name, 4, batch, accum, true);
        let mut args = launch_args(world);
        args.extend(["train".into(), "--config".into(), cfg.display().to_string()]);
        let out = umgen(&args.iter().map(String::as_str).collect::<Vec<_>>());
        let log = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{log}");
        assert!(log.contains(&format!("{world} ranks over tcp")), "{log}");
        let worst = largest_difference(&weights(&dir.path().join(&name)));
        eprintln!("{world} ranks: largest parameter difference {worst:e} (other data: {other_data:e})");
        assert!(
            worst < 1e-3 * other_data,
            "{world} ranks: largest difference {worst}"
        );
        let metrics = std::fs::read_to_string(dir.path().join(&name).join("metrics.jsonl")).unwrap();
        assert_eq!(metrics.lines().count(), 4, "only rank 0 writes metrics");
    }

    // A 2-rank launch killed (SIGKILL to the launcher: its ranks follow) once a checkpoint exists and
    // then resumed ends exactly where the uninterrupted 2-rank run ends.
    let launch = |cfg: &Path, extra: &[&str]| {
        let port = free_port();
        let mut args = vec!["launch", "--nproc-per-node", "2", "--master-port", &port, "--"];
        args.extend(["train", "--config", cfg.to_str().unwrap()]);
        args.extend(extra);
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_umgen"));
        cmd.args(args).env("NO_COLOR", "1");
        cmd
    };
    let out = launch(&config(dir.path(), &data, "straight", 30, 3), &[])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let cfg = config(dir.path(), &data, "resumed", 30, 3);
    let mut child = launch(&cfg, &[]).stderr(Stdio::null()).spawn().unwrap();
    let ckpt = dir.path().join("resumed/checkpoints/step-000000004");
    let t0 = Instant::now();
    while !ckpt.exists() {
        assert!(t0.elapsed() < Duration::from_secs(120), "no checkpoint appeared");
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    assert!(!child.wait().unwrap().success(), "killed before the end");
    // The ranks notice that their launcher is gone and exit.
    std::thread::sleep(Duration::from_secs(3));
    let out = launch(&cfg, &["--resume"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (a, b) = (
        weights(&dir.path().join("straight")),
        weights(&dir.path().join("resumed")),
    );
    assert!(
        a == b,
        "a resumed 2-rank run repeats the uninterrupted one exactly"
    );

    // A time limit stops both ranks at the same logging step (step 1 logs), with a checkpoint from which
    // the run finishes exactly as the uninterrupted one.
    let cfg = config(dir.path(), &data, "limited", 30, 3);
    let out = launch(&cfg, &["--time-limit", "1e-6"]).output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("time limit reached at step 1"), "{log}");
    assert!(dir.path().join("limited/checkpoints/step-000000001").exists());
    let out = launch(&cfg, &["--resume"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(weights(&dir.path().join("limited")) == a);
}

/// `train.shard_optimizer`: 2 and 3 ranks that each step their share of the parameters end with the
/// weights of the unsharded run to the bit; a sharded run stopped by a time limit resumes exactly; and
/// checkpoints pass between sharded and unsharded runs (the gathered moments are the unsharded ones, or
/// the resumed run would drift).
#[test]
fn a_sharded_optimizer_steps_and_resumes_as_an_unsharded_one() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 40).unwrap();
    let train = |world: usize, name: &str, batch: usize, sharded: bool, extra: &[&str]| {
        let cfg = config(dir.path(), &data, name, 8, batch);
        let mut args = launch_args(world);
        args.extend(["train".into(), "--config".into(), cfg.display().to_string()]);
        args.extend(["--set".into(), format!("train.shard_optimizer={sharded}")]);
        args.extend(extra.iter().map(|s| s.to_string()));
        let out = umgen(&args.iter().map(String::as_str).collect::<Vec<_>>());
        let log = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{name}: {log}");
        assert_eq!(
            log.contains(&format!("optimizer state sharded over {world} ranks")),
            sharded,
            "{name}: {log}"
        );
        weights(&dir.path().join(name))
    };
    for (world, batch) in [(2, 3), (3, 2)] {
        let plain = train(world, &format!("plain{world}"), batch, false, &[]);
        let sharded = train(world, &format!("sharded{world}"), batch, true, &[]);
        assert!(
            sharded == plain,
            "{world} ranks: sharded weights equal the unsharded ones"
        );
    }
    let reference = weights(&dir.path().join("plain2"));
    // Stopped at step 1 (a checkpoint), then resumed: sharded → sharded, sharded → unsharded, and
    // unsharded → sharded.
    for (name, first, then) in [("ss", true, true), ("su", true, false), ("us", false, true)] {
        train(2, name, 3, first, &["--time-limit", "1e-6"]);
        assert!(dir.path().join(name).join("checkpoints/step-000000001").exists());
        let resumed = train(2, name, 3, then, &["--resume"]);
        assert!(
            resumed == reference,
            "{name}: a resumed run repeats the uninterrupted one"
        );
    }
    // One rank has nothing to share, and says so.
    let one = config(dir.path(), &data, "one", 2, 6);
    let out = umgen(&[
        "train",
        "--config",
        one.to_str().unwrap(),
        "--set",
        "train.shard_optimizer=true",
    ]);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{log}");
    assert!(log.contains("one rank has nothing to share"), "{log}");
}

/// Starts a long 2-rank run and returns the launcher and the pid of rank 1.
fn start_long_run(dir: &Path, data: &Path, name: &str) -> (std::process::Child, u32, mpsc::Receiver<String>) {
    let cfg = config(dir, data, name, 1_000_000, 2);
    let mut child = Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args([
            "launch",
            "--nproc-per-node",
            "2",
            "--master-port",
            &free_port(),
            "--",
            "train",
        ])
        .args(["--config", cfg.to_str().unwrap(), "--dist-timeout", "5"])
        .env("NO_COLOR", "1")
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let t0 = Instant::now();
    let mut pid = None;
    // Wait until rank 1 has started and training is under way (a logged step).
    loop {
        let line = rx
            .recv_timeout(Duration::from_secs(120))
            .expect("launcher output");
        if let Some(rest) = line.split("started rank 1 (pid ").nth(1) {
            pid = rest.trim_end_matches(')').parse::<u32>().ok();
        }
        if line.contains("step 2/") {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "no training progress");
    }
    (child, pid.expect("rank 1's pid"), rx)
}

fn wait_failed(child: &mut std::process::Child, within: Duration) -> Duration {
    let t0 = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(!status.success(), "the launcher must fail");
            return t0.elapsed();
        }
        assert!(
            t0.elapsed() < within,
            "the launcher is still running after {within:?}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// `umgen tokenizer train` of the tiny image and map tokenizers: 2 ranks × 2 rasters against one rank × 4,
/// in the linear regime (AdamW ε = 1), every weight and codebook tensor of the written tokenizer. The map
/// tokenizer's Dice term is a ratio of sums over the batch, which the ranks complete with each other's.
#[test]
fn tokenizer_ranks_match_one_rank_on_the_same_global_batch() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 40).unwrap();
    let tiny = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/tiny.toml");
    let run = |modality: &str, name: &str, world: usize, batch: usize| {
        let out = dir.path().join(format!("{modality}-{name}"));
        let mut args = if world > 1 { launch_args(world) } else { Vec::new() };
        args.extend(
            [
                "tokenizer",
                "train",
                "--config",
                tiny.to_str().unwrap(),
                "--modality",
                modality,
            ]
            .map(String::from),
        );
        args.extend([
            "--data".into(),
            data.display().to_string(),
            "--out".into(),
            out.display().to_string(),
        ]);
        for kv in [
            "steps=4".to_string(),
            format!("batch_size={batch}"),
            "eps=1.0".into(),
            "lr=0.3".into(),
            "warmup=1".into(),
            "log_every=1".into(),
            "threads=1".into(),
        ] {
            args.extend(["--set".into(), format!("modality.{modality}.vq_train.{kv}")]);
        }
        let out_ = umgen(&args.iter().map(String::as_str).collect::<Vec<_>>());
        let log = String::from_utf8_lossy(&out_.stderr).into_owned();
        assert!(out_.status.success(), "{name}: {log}");
        if world > 1 {
            assert!(log.contains(&format!("{world} ranks over tcp")), "{log}");
            let metrics = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
            assert_eq!(metrics.lines().count(), 4, "only rank 0 writes metrics");
        }
        safetensors_f32(&out.join("vq.safetensors"))
    };
    for modality in ["image", "map"] {
        let reference = run(modality, "one", 1, 4);
        let other_data = largest_difference(&run(modality, "half", 1, 2), &reference);
        let ranks = largest_difference(&run(modality, "ranks2", 2, 2), &reference);
        eprintln!("{modality} tokenizer, 2 ranks: largest difference {ranks:e} (other data: {other_data:e})");
        assert!(other_data > 1e-4, "{modality}: {other_data}");
        assert!(
            ranks < 1e-3 * other_data,
            "{modality}, 2 ranks: largest difference {ranks}"
        );
    }
}

#[test]
fn a_killed_or_stopped_rank_fails_the_launcher_within_the_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 40).unwrap();
    // Tokenize once, so that both runs start training at once.
    let warm = config(dir.path(), &data, "warm", 1, 2);
    assert!(
        umgen(&["train", "--config", warm.to_str().unwrap()])
            .status
            .success()
    );

    let (mut launcher, pid, _rx) = start_long_run(dir.path(), &data, "killed");
    Command::new("kill")
        .args(["-KILL", &pid.to_string()])
        .status()
        .unwrap();
    wait_failed(&mut launcher, Duration::from_secs(10));

    // A stopped rank is alive to the launcher; the watchdog (timeout 5 s) must notice and name it.
    let (mut launcher, pid, rx) = start_long_run(dir.path(), &data, "stopped");
    Command::new("kill")
        .args(["-STOP", &pid.to_string()])
        .status()
        .unwrap();
    let took = wait_failed(&mut launcher, Duration::from_secs(30));
    let _ = Command::new("kill")
        .args(["-KILL", &pid.to_string()])
        .stderr(Stdio::null())
        .status();
    let log: Vec<String> = rx.try_iter().collect();
    assert!(
        log.iter().any(|l| l.contains("rank 1 sent nothing for 5 s")),
        "after {took:?}: {log:?}"
    );
}
