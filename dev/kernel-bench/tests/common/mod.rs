//! Helpers shared by the kernel tools' test files.
#![allow(dead_code, clippy::unwrap_used)]

use std::process::{Command, Output};

/// Runs the `umgen-kernel-bench` binary under test with plain (uncoloured, default-level) logs.
pub fn kernel_bench(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_umgen-kernel-bench"))
        .args(args)
        .env("NO_COLOR", "1")
        .env_remove("UMGEN_LOG")
        .output()
        .unwrap()
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
