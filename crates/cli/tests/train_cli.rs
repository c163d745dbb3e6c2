//! `umgen train` end to end on a tiny imported SUMO fixture: the loss falls, a run killed with SIGKILL and
//! resumed repeats the uninterrupted run's losses exactly, damaged checkpoints fall back, other configs
//! are refused, and TensorBoard reads the event files.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};
use umgen::UmgenConfig;
use umgen::data::Dataset;
use umgen_tests::fixtures::{tiny_dataset, train_tokenizers};

/// The fixture's config: tiny tokenizers (trained here for two steps) and a tiny backbone.
fn config_text(dir: &Path, data: &Path, out: &str, steps: u64) -> String {
    let tok = |m: &str| dir.join("tok").join(m).display().to_string();
    format!(
        "[layout]\norder = [\"ego\", \"map\", \"agent\", \"image\"]\n\
         [modality.agent]\nmax_agents = 4\n\
         [modality.map]\nraster = [32, 32]\ngrid = [4, 4]\ncodebook_size = 32\ntokenizer = \"{}\"\n\
         [modality.map.vq]\nbase = 8\nmult = [1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.map.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n\
         [modality.image]\nsize = [32, 64]\ngrid = [2, 4]\ncodebook_size = 32\ntokenizer = \"{}\"\n\
         [modality.image.vq]\nbase = 8\nmult = [1, 1, 2, 2, 2]\nres_blocks = 1\nz_channels = 4\nembed_dim = 4\nattention = false\ngroups = 4\n\
         [modality.image.vq_train]\nsteps = 2\nbatch_size = 2\nthreads = 1\n\
         [backbone]\nd_model = 32\nheads = 2\nmlp_ratio = 2\ndropout = 0.1\nego_hist_layers = 1\nego_env_layers = 1\ntar_layers = 1\noar_layers = 1\nmax_frames = 4\n\
         [train]\nout_dir = \"{}\"\ntokens = \"{}\"\ndata = \"{}\"\nsteps = {steps}\nbatch_size = 2\nframes = 2\nlr = 3e-3\nwarmup = 3\nlog_every = 1\ncheckpoint_every = 5\nkeep_checkpoints = 3\n",
        tok("map"),
        tok("image"),
        dir.join(out).display(),
        dir.join("tokens").display(),
        data.display()
    )
}

/// A fixture dataset, its tokenizers, and a config file per run directory name.
struct Fixture {
    dir: tempfile::TempDir,
    data: PathBuf,
}

impl Fixture {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let data = tiny_dataset(dir.path(), 40).unwrap();
        let ds = Dataset::open(&data).unwrap();
        let bare = UmgenConfig::from_toml_str(&config_text(dir.path(), &data, "unused", 1)).unwrap();
        train_tokenizers(&bare, &ds, &dir.path().join("tok")).unwrap();
        Self { dir, data }
    }

    fn config(&self, run: &str, steps: u64) -> PathBuf {
        let p = self.dir.path().join(format!("{run}.toml"));
        std::fs::write(&p, config_text(self.dir.path(), &self.data, run, steps)).unwrap();
        p
    }

    fn run_dir(&self, run: &str) -> PathBuf {
        self.dir.path().join(run)
    }
}

fn umgen(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .unwrap()
}

fn ok(out: Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "stderr: {err}");
    err
}

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
    let fx = Fixture::new();
    // The uninterrupted run.
    let cfg_a = fx.config("a", 30);
    let log = ok(umgen(&["train", "--config", cfg_a.to_str().unwrap()]));
    assert!(log.contains("tokenized"), "the first run tokenizes: {log}");
    let a = losses(&fx.run_dir("a"));
    assert_eq!(a.len(), 30);
    let first = a[&1];
    let last: f64 = (26..=30).map(|s| a[&s]).sum::<f64>() / 5.0;
    assert!(last < 0.75 * first, "the loss falls: {first} → {last}");

    // The same run, killed with SIGKILL once a checkpoint exists, then resumed.
    let cfg_b = fx.config("b", 30);
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

    // A damaged newest checkpoint is detected and the previous one is used.
    let newest = fx.run_dir("b").join("checkpoints/step-000000030");
    let w = newest.join("model.safetensors");
    let mut bytes = std::fs::read(&w).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x55;
    std::fs::write(&w, bytes).unwrap();
    let cfg_b35 = fx.config("b", 35);
    let log = ok(umgen(&[
        "train",
        "--config",
        cfg_b35.to_str().unwrap(),
        "--resume",
    ]));
    assert!(
        log.contains("skipping checkpoint") && log.contains("checksum") && log.contains("step 25"),
        "{log}"
    );

    // Another model refuses the checkpoints and names the difference.
    let out = umgen(&[
        "train",
        "--config",
        cfg_b35.to_str().unwrap(),
        "--resume",
        "--set",
        "backbone.d_model=48",
        "--set",
        "backbone.heads=3",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("does not match this run")
            && err.contains("backbone (d_model, heads)"),
        "{err}"
    );

    // TensorBoard's own reader loads the scalars (CI sets UMGEN_TB_PYTHON to a Python with tensorboard).
    if let Ok(python) = std::env::var("UMGEN_TB_PYTHON") {
        let script =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/python/check_tensorboard.py");
        let out = Command::new(python)
            .arg(script)
            .arg(fx.run_dir("a").join("tb"))
            .args(["loss", "30"])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

#[test]
fn export_writes_a_bundle_that_opens_and_refuses_damage() {
    let fx = Fixture::new();
    let cfg = fx.config("e", 2);
    ok(umgen(&["train", "--config", cfg.to_str().unwrap()]));
    let run = fx.run_dir("e");
    let f32_dir = fx.dir.path().join("bundle-f32");
    let bf16_dir = fx.dir.path().join("bundle-bf16");
    ok(umgen(&[
        "export",
        "--checkpoint",
        run.to_str().unwrap(),
        "--out",
        f32_dir.to_str().unwrap(),
    ]));
    ok(umgen(&[
        "export",
        "--checkpoint",
        run.to_str().unwrap(),
        "--out",
        bf16_dir.to_str().unwrap(),
        "--dtype",
        "bf16",
    ]));
    let a = umgen::Bundle::open(&f32_dir).unwrap();
    let b = umgen::Bundle::open(&bf16_dir).unwrap();
    assert_eq!(a.manifest.step, 2);
    assert_eq!(a.manifest.fingerprint, b.manifest.fingerprint);
    assert!(a.manifest.files.contains_key("tokenizers/map/vq.safetensors"));
    assert_eq!(a.manifest.layout["n"], b.manifest.layout["n"]);
    // bf16 = f32 rounded: same names and shapes, values within bf16's relative step.
    let (wa, wb) = (a.weights().unwrap(), b.weights().unwrap());
    let (sa, sb) = (
        safetensors::SafeTensors::deserialize(&wa).unwrap(),
        safetensors::SafeTensors::deserialize(&wb).unwrap(),
    );
    assert_eq!(sa.names().len(), sb.names().len());
    for (name, va) in sa.tensors() {
        let vb = sb.tensor(&name).unwrap();
        assert_eq!((vb.dtype(), vb.shape()), (safetensors::Dtype::BF16, va.shape()));
        for (x, h) in va.data().chunks_exact(4).zip(vb.data().chunks_exact(2)) {
            let x = f32::from_le_bytes([x[0], x[1], x[2], x[3]]);
            let y = f32::from_bits(u32::from(u16::from_le_bytes([h[0], h[1]])) << 16);
            assert!((x - y).abs() <= x.abs() / 256.0, "{name}: {x} vs {y}");
        }
    }
    // Outside readers: Python's safetensors (CI's UMGEN_TB_PYTHON has it).
    if let Ok(python) = std::env::var("UMGEN_TB_PYTHON") {
        let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/python/check_bundle.py");
        for (dir, dtype) in [(&f32_dir, "F32"), (&bf16_dir, "BF16")] {
            let out = Command::new(&python)
                .arg(&script)
                .arg(dir)
                .args([dtype, "time", "oar_heads.heads.0.weight"])
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
    }
    // Generation from the bundle: tokens in their vocabularies, a forced left turn turns left, seeds repeat.
    let ds = Dataset::open(&fx.data).unwrap();
    let context = format!("{}:{}:2", fx.data.display(), ds.clips()[0].id);
    let control = fx.dir.path().join("left.toml");
    std::fs::write(&control, "[[ego]]\nfrom = 0\nto = 4\ndx = 2.0\ndtheta = 0.15\n").unwrap();
    let generate = |bundle: &Path, out: &str, seed: &str| {
        let out = fx.dir.path().join(out);
        let args = [
            "generate",
            "--bundle",
            bundle.to_str().unwrap(),
            "--context",
            &context,
            "--frames",
            "4",
            "--scenes",
            "2",
            "--control",
            control.to_str().unwrap(),
            "--seed",
            seed,
            "--out",
            out.to_str().unwrap(),
        ];
        ok(umgen(&args));
        out
    };
    let g1 = generate(&bf16_dir, "gen1", "3");
    let tokens: serde_json::Value =
        serde_json::from_slice(&std::fs::read(g1.join("tokens.json")).unwrap()).unwrap();
    let segments = b.manifest.layout["segments"].as_array().unwrap().clone();
    for scene in tokens["scenes"].as_array().unwrap() {
        let frames = scene.as_array().unwrap();
        assert_eq!(frames.len(), 2 + 4, "2 context + 4 generated frames");
        for f in frames {
            let f: Vec<u64> = f
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_u64().unwrap())
                .collect();
            for seg in &segments {
                let (off, n, vocab) = (
                    seg["offset"].as_u64().unwrap() as usize,
                    seg["tokens"].as_u64().unwrap() as usize,
                    seg["vocab_size"].as_u64().unwrap(),
                );
                assert!(
                    f[off..off + n].iter().all(|&id| id < vocab),
                    "{}",
                    seg["modality"]
                );
            }
        }
    }
    let scenes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(g1.join("scenes.json")).unwrap()).unwrap();
    for clip in scenes.as_array().unwrap() {
        let headings: Vec<f64> = clip["frames"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["ego"]["heading"].as_f64().unwrap())
            .collect();
        let turns: Vec<f64> = headings.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(
            turns.iter().all(|d| *d > 0.1 && *d < 0.2),
            "a left turn each frame: {headings:?}"
        );
    }
    assert!(g1.join("rollout.gif").exists());
    let g2 = generate(&bf16_dir, "gen2", "3");
    assert_eq!(
        std::fs::read(g1.join("tokens.json")).unwrap(),
        std::fs::read(g2.join("tokens.json")).unwrap()
    );
    // An agent placed by the control file appears where it was put (within a bin), with its velocity.
    std::fs::write(
        &control,
        "[[agent]]\nslot = 1\nfrom = 0\nto = 4\nx = 12.0\ny = 3.5\nvx = 6.0\nvy = -1.0\n",
    )
    .unwrap();
    let g4 = generate(&bf16_dir, "gen4", "3");
    let scenes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(g4.join("scenes.json")).unwrap()).unwrap();
    for clip in scenes.as_array().unwrap() {
        for f in clip["frames"].as_array().unwrap() {
            let a = f["agents"]
                .as_array()
                .unwrap()
                .iter()
                .find(|a| a["track_id"] == 1)
                .expect("the controlled agent");
            for (k, want) in [("x", 12.0), ("y", 3.5), ("vx", 6.0), ("vy", -1.0)] {
                let got = a[k].as_f64().unwrap();
                assert!((got - want).abs() < 0.5, "{k}: {got} vs {want}");
            }
            assert_eq!(a["category"], "vehicle");
        }
    }
    let g3 = generate(&bf16_dir, "gen3", "4");
    assert_ne!(
        std::fs::read(g1.join("tokens.json")).unwrap(),
        std::fs::read(g3.join("tokens.json")).unwrap()
    );

    // A missing or replaced file is refused, naming it; so is an existing output directory.
    std::fs::remove_file(bf16_dir.join("tokenizers/image/vq.json")).unwrap();
    let e = umgen::Bundle::open(&bf16_dir).unwrap_err().to_string();
    assert!(
        e.contains("tokenizers/image/vq.json") && e.contains("unreadable"),
        "{e}"
    );
    let w = f32_dir.join("model.safetensors");
    let mut bytes = std::fs::read(&w).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 1;
    std::fs::write(&w, bytes).unwrap();
    let e = umgen::Bundle::open(&f32_dir).unwrap_err().to_string();
    assert!(e.contains("model.safetensors") && e.contains("checksum"), "{e}");
    let out = umgen(&[
        "export",
        "--checkpoint",
        run.to_str().unwrap(),
        "--out",
        f32_dir.to_str().unwrap(),
    ]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("already exists"));
}
