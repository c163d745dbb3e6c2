//! Helpers shared by the CLI test files (each test file is its own crate and uses some of them).
#![allow(dead_code, clippy::unwrap_used, clippy::panic)]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

/// Runs the `umgen` binary under test with plain (uncoloured, default-level) logs.
pub fn umgen(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_umgen"))
        .args(args)
        .env("NO_COLOR", "1")
        .env_remove("UMGEN_LOG")
        .output()
        .unwrap()
}

/// `umgen eval` of the rollout in `generated` against the test split of the dataset `reference`, every
/// 50th real frame; asserts success and returns the log.
pub fn eval_test_split(generated: &Path, reference: &str) -> String {
    let dir = generated.to_str().unwrap();
    ok(umgen(&[
        "eval",
        "--generated",
        dir,
        "--reference",
        reference,
        "--split",
        "test",
        "--stride",
        "50",
    ]))
}

/// Bytes of a child's output as text.
pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Asserts success and returns stderr (the log).
pub fn ok(out: Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "stderr: {err}");
    err
}

/// `umgen generate` arguments that draw every id from a flattened softmax, seed 4: a barely trained
/// model's frames then differ from one to the next.
pub const LOOSE_DRAW: [&str; 6] = ["--seed", "4", "--top-k", "0", "--temperature", "1.5"];

/// Trains the fixture's run `run` for 2 steps on its config as `edit` rewrites it, exports it into
/// `<fixture>/bundle` and returns that directory.
pub fn fixture_bundle(
    fx: &umgen_tests::run_fixture::Fixture,
    run: &str,
    edit: impl FnOnce(String) -> String,
) -> std::path::PathBuf {
    let cfg = fx.config(run, 2).unwrap();
    let text = std::fs::read_to_string(&cfg).unwrap();
    std::fs::write(&cfg, edit(text)).unwrap();
    ok(umgen(&["train", "--config", cfg.to_str().unwrap()]));
    let bundle = fx.dir.path().join("bundle");
    ok(umgen(&[
        "export",
        "--checkpoint",
        fx.run_dir(run).to_str().unwrap(),
        "--out",
        bundle.to_str().unwrap(),
    ]));
    bundle
}

/// A TCP port free right now (for rendezvous in tests).
pub fn free_port() -> String {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
        .to_string()
}

/// `umgen launch` of `world` local ranks meeting on a free port, up to the `--` before the command.
pub fn launch_args(world: usize) -> Vec<String> {
    let port = free_port();
    [
        "launch",
        "--nproc-per-node",
        &world.to_string(),
        "--master-port",
        &port,
        "--",
    ]
    .map(String::from)
    .to_vec()
}

/// Runs `tests/python/<script>` with `args` in the Python of `UMGEN_TB_PYTHON` (CI's venv with tensorboard,
/// safetensors and PyTorch), the PyTorch runner (`runners/python`) on its path, and asserts success;
/// skipped without that variable.
pub fn python_check(script: &str, args: &[&std::ffi::OsStr]) {
    let Ok(python) = std::env::var("UMGEN_TB_PYTHON") else {
        return;
    };
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let out = Command::new(python)
        .arg(root.join("tests/python").join(script))
        .args(args)
        .env("PYTHONPATH", root.join("runners/python"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{script}: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Every f32 tensor of a safetensors file, by name.
pub fn safetensors_f32(path: &Path) -> BTreeMap<String, Vec<f32>> {
    let bytes = std::fs::read(path).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    st.tensors()
        .into_iter()
        .map(|(name, view)| {
            let v = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            (name, v)
        })
        .collect()
}

/// The largest |a − b| over tensors of the same names (which must match).
pub fn largest_difference(a: &BTreeMap<String, Vec<f32>>, b: &BTreeMap<String, Vec<f32>>) -> f32 {
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    let mut worst = 0f32;
    for (k, want) in b {
        assert_eq!(a[k].len(), want.len(), "{k}");
        for (x, y) in a[k].iter().zip(want) {
            worst = worst.max((x - y).abs());
        }
    }
    worst
}
