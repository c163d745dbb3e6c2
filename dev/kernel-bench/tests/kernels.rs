//! The kernel tools on the CPU: the training kernels' CPU paths agree with burn's operations (the tools'
//! agreement columns, read back), and a decoding step's parts are timed. On a GPU the same commands check
//! the CUDA kernels (build with `--features cuda` and pass `--device cuda:0`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{kernel_bench, ok, text};

/// Runs a tool that must fail cleanly and returns its stderr.
fn failure(args: &[&str]) -> String {
    let out = kernel_bench(args);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "stderr: {err}");
    assert!(!err.contains("panicked") && err.starts_with("error: "), "{err}");
    err
}

/// `umgen-kernel-bench attention --iters 1` with `args`: the header and each row as (case, numbers: block MiB,
/// training kernels' ms, decomposed ms, the four errors, the two pool sizes). Every row is the tiled
/// kernel's (the CPU has no other).
fn attention_table(args: &[&str]) -> (String, Vec<(String, Vec<f64>)>) {
    let out = kernel_bench(&[&["attention", "--iters", "1"], args].concat());
    let table = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let rows = table
        .lines()
        .filter(|l| {
            l.split_whitespace()
                .nth(2)
                .is_some_and(|c| c.parse::<f64>().is_ok())
        })
        .map(|l| {
            let mut cols = l.split_whitespace();
            let case = cols.next().unwrap_or_default().to_string();
            assert_eq!(cols.next(), Some("tiled"), "{table}");
            (case, cols.map(|c| c.parse().unwrap()).collect())
        })
        .collect();
    (table, rows)
}

#[test]
fn attention_agrees_with_the_decomposed_attention_and_names_bad_cases() {
    let (table, rows) = attention_table(&["--cases", "2x2x300x300x8c,1x2x40x90x8"]);
    let cases: Vec<&str> = rows.iter().map(|(c, _)| c.as_str()).collect();
    assert_eq!(cases, ["2x2x300x300x8c", "1x2x40x90x8"], "{table}");
    for (_, cols) in &rows {
        // The default block size, 1024 MiB.
        assert_eq!(cols[0], 1024.0, "{table}");
        assert!(cols[1] > 0.0 && cols[2] > 0.0, "{table}");
        // Output and the three gradients agree to f32 rounding.
        assert!(cols[3..7].iter().all(|&e| e < 1e-5), "{table}");
    }
    // Blocks of 1 MiB split the 300 causal queries in two (192 + 108 rows); one row per size, each
    // agreeing with the decomposed attention.
    let (table, rows) = attention_table(&["--cases", "2x2x300x300x8c", "--block-mib", "1,64"]);
    let sizes: Vec<f64> = rows.iter().map(|(_, r)| r[0]).collect();
    assert_eq!(sizes, [1.0, 64.0], "{table}");
    assert!(
        rows.iter().all(|(_, r)| r[3..7].iter().all(|&e| e < 1e-5)),
        "{table}"
    );
    // bf16 products on the tiled side: close to the f32 reference, but not equal to it.
    let (table, rows) = attention_table(&["--cases", "2x2x300x300x8c", "--precision", "bf16"]);
    assert!(table.contains("products in bf16"), "{table}");
    assert_eq!(rows.len(), 1, "{table}");
    assert!(rows[0].1[3..7].iter().all(|&e| e > 1e-6 && e < 3e-2), "{table}");
    let err = failure(&["attention", "--cases", "2x2x30x20x8c"]);
    assert!(err.contains("2x2x30x20x8c") && err.contains("LK ≥ LQ"), "{err}");
    let err = failure(&["attention", "--kernels", "fused"]);
    assert!(err.contains("--kernels fused") && err.contains("CUDA"), "{err}");
    let err = failure(&["attention", "--step", "16,48"]);
    assert!(
        err.contains("--step") && err.contains("48") && err.contains("[16, 32, 64]"),
        "{err}"
    );
}

#[test]
fn layers_agree_with_burns_operations_and_checks_its_shape() {
    let out = kernel_bench(&["layers", "--shape", "2,5,7,64", "--heads", "2", "--iters", "1"]);
    let table = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let rows: Vec<Vec<f64>> = ["layer norm", "attention over time, 2h", "cross-entropy, 8192 ids"]
        .iter()
        .map(|name| {
            let line = table
                .lines()
                .find(|l| l.starts_with(name))
                .unwrap_or_else(|| panic!("{table}"));
            line[name.len()..]
                .split_whitespace()
                .filter(|c| *c != "-")
                .map(|c| c.parse().unwrap())
                .collect()
        })
        .collect();
    for (i, cols) in rows.iter().enumerate() {
        // Two times, then the errors of the output and the gradients (two, or the cross-entropy's one):
        // f32 rounding on the CPU.
        assert_eq!(cols.len(), if i == 2 { 4 } else { 5 }, "{table}");
        assert!(cols[0] > 0.0 && cols[1] > 0.0, "{table}");
        assert!(cols[2..].iter().all(|&e| e < 1e-5), "{table}");
    }
    let err = failure(&["layers", "--shape", "2,5,7,64", "--heads", "3"]);
    assert!(err.contains("--heads 3") && err.contains("multiple"), "{err}");
    let err = failure(&["layers", "--shape", "2,5,64"]);
    assert!(err.contains("four sizes"), "{err}");
    let err = failure(&["layers", "--vocab", "0"]);
    assert!(err.contains("--vocab"), "{err}");
}

#[test]
fn a_decoding_steps_parts_are_timed() {
    let tiny = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/tiny.toml");
    let out = kernel_bench(&["decode", "--config", tiny, "--batch", "2"]);
    let table = text(&out.stdout);
    ok(out);
    let parts: Vec<f64> = table
        .lines()
        .skip_while(|l| !l.starts_with("parts of one decoding step"))
        .skip(1)
        .map(|l| l.split_whitespace().last().unwrap().parse::<f64>().unwrap())
        .collect();
    assert_eq!(parts.len(), 5, "{table}");
    assert!(parts.iter().all(|&ms| ms > 0.0), "{table}");
    // The CPU has only the rounds top-k.
    assert!(
        table.contains("device draw, top-16 by rounds") && !table.contains("by reduce"),
        "{table}"
    );
    let out = kernel_bench(&["decode", "--config", tiny, "--batch", "0"]);
    assert!(!out.status.success() && text(&out.stderr).contains("--batch"));
}
