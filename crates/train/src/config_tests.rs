//! Training settings: kernel choices that leave the run's identity alone, and values no run can use.

use super::*;

#[test]
fn kernel_settings_parse_are_checked_and_resuming_may_change_them() {
    let cublas = TrainConfig::default();
    let parse = |json: &str| serde_json::from_str::<TrainConfig>(json);
    let burn = parse(r#"{"matmul": "burn"}"#).expect("train.matmul = burn");
    let named = parse(r#"{"matmul": "named"}"#).expect("train.matmul = named");
    assert_eq!(
        (cublas.matmul, named.matmul, burn.matmul),
        (MatmulKernel::Cublas, MatmulKernel::Named, MatmulKernel::Burn)
    );
    assert_eq!(named.identity(), burn.identity());
    assert_eq!(named.identity(), cublas.identity());
    // A setting that changes the run still does.
    let lr = parse(r#"{"lr": 0.5}"#).expect("lr");
    assert_ne!(named.identity(), lr.identity());
    let blocks = parse(r#"{"attention_block_mib": 256}"#).expect("attention_block_mib");
    assert_eq!(named.identity(), blocks.identity());
    let tiled = parse(r#"{"attention": "tiled"}"#).expect("attention = tiled");
    let fused = parse(r#"{"attention": "fused"}"#).expect("attention = fused");
    assert_eq!(
        (named.attention, tiled.attention, fused.attention),
        (
            AttentionKernel::Flash2,
            AttentionKernel::Tiled,
            AttentionKernel::Fused
        )
    );
    assert_eq!(named.identity(), tiled.identity());
    assert_eq!(named.identity(), fused.identity());
    let burn_norm = parse(r#"{"norm": "burn"}"#).expect("norm = burn");
    assert_eq!(
        (named.norm, burn_norm.norm),
        (NormKernel::Fused, NormKernel::Burn)
    );
    assert_eq!(named.identity(), burn_norm.identity());
    let burn_gelu = parse(r#"{"gelu": "burn"}"#).expect("gelu = burn");
    assert_eq!(
        (named.gelu, burn_gelu.gelu),
        (GeluKernel::Fused, GeluKernel::Burn)
    );
    assert_eq!(named.identity(), burn_gelu.identity());
    let burn_xent = parse(r#"{"xent": "burn"}"#).expect("xent = burn");
    assert_eq!(
        (named.xent, burn_xent.xent),
        (XentKernel::Fused, XentKernel::Burn)
    );
    assert_eq!(named.identity(), burn_xent.identity());
    let side = parse(r#"{"kernel_stream": "side"}"#).expect("kernel_stream = side");
    assert_eq!(
        (named.kernel_stream, side.kernel_stream),
        (KernelStream::Cubecl, KernelStream::Side)
    );
    assert_eq!(named.identity(), side.identity());
    let burn_adamw = parse(r#"{"adamw": "burn"}"#).expect("adamw = burn");
    assert_eq!(
        (named.adamw, burn_adamw.adamw),
        (AdamWChoice::Fused, AdamWChoice::Burn)
    );
    assert_eq!(named.identity(), burn_adamw.identity());
    let caller = parse(r#"{"launch_thread": "caller"}"#).expect("launch_thread = caller");
    assert_eq!(
        (named.launch_thread, caller.launch_thread),
        (LaunchThread::Device, LaunchThread::Caller)
    );
    assert_eq!(named.identity(), caller.identity());
    let e = parse(r#"{"adamw": "apex"}"#).unwrap_err().to_string();
    assert!(e.contains("apex") && e.contains("fused"), "{e}");
    let e = parse(r#"{"kernel_stream": "main"}"#).unwrap_err().to_string();
    assert!(e.contains("main") && e.contains("cubecl"), "{e}");
    let e = parse(r#"{"norm": "fast"}"#).unwrap_err().to_string();
    assert!(e.contains("fast") && e.contains("fused"), "{e}");
    let recompute = parse(r#"{"recompute": true}"#).expect("recompute = true");
    assert!(recompute.recompute && !named.recompute);
    assert_eq!(named.identity(), recompute.identity());
    let e = parse(r#"{"attention": "flash"}"#).unwrap_err().to_string();
    assert!(e.contains("flash") && e.contains("flash2"), "{e}");
    let e = parse(r#"{"attention_block_mib": 0}"#)
        .expect("parses")
        .select_kernels()
        .unwrap_err();
    assert!(e.to_string().contains("train.attention_block_mib = 0"), "{e}");
    let step = parse(r#"{"attention_step": 16}"#).expect("attention_step = 16");
    assert_eq!(named.identity(), step.identity());
    let e = parse(r#"{"attention_step": 48}"#)
        .expect("parses")
        .select_kernels()
        .unwrap_err();
    assert!(e.to_string().contains("train.attention_step = 48"), "{e}");
    let e = parse(r#"{"matmul": "tma"}"#).unwrap_err().to_string();
    assert!(
        e.contains("tma") && e.contains("cublas") && e.contains("named") && e.contains("burn"),
        "{e}"
    );
}

#[test]
fn values_no_run_can_use_are_named_by_key() {
    assert_eq!(TrainConfig::default().problem(), None);
    let cases: [(&str, &str, &str); 14] = [
        (r#"{"lr": -1.0}"#, "lr", "-1 must be a positive number"),
        (r#"{"lr": 0.0}"#, "lr", "0 must be a positive number"),
        (
            r#"{"weight_decay": -5.0}"#,
            "weight_decay",
            "-5 must be 0 or a positive number",
        ),
        (r#"{"batch_size": 0}"#, "batch_size", "0 must be 1 or more"),
        (r#"{"log_every": 0}"#, "log_every", "0 must be 1 or more"),
        (
            r#"{"keep_checkpoints": 0}"#,
            "keep_checkpoints",
            "0 must be 1 or more",
        ),
        (r#"{"beta1": 1.0}"#, "beta1", "1 must be at least 0 and below 1"),
        (
            r#"{"min_lr_ratio": 2.0}"#,
            "min_lr_ratio",
            "2 must be a fraction of the peak, 0 to 1",
        ),
        (
            r#"{"grad_clip": -1.0}"#,
            "grad_clip",
            "-1 must be 0 (no clipping) or a positive norm",
        ),
        (
            r#"{"bucket_mib": 0.0}"#,
            "bucket_mib",
            "0 must be a positive size",
        ),
        (
            r#"{"eps": 1e-60}"#,
            "eps",
            "0.000000000000000000000000000000000000000000000000000000000001 must be a positive number that f32 holds",
        ),
        (r#"{"attention_step": 48}"#, "attention_step", "attention step 48"),
        (
            r#"{"max_skipped_steps": 0}"#,
            "max_skipped_steps",
            "0 must be 1 or more",
        ),
        (
            r#"{"prior_drop": 1.5}"#,
            "prior_drop",
            "1.5 must be a probability (0 to 1)",
        ),
    ];
    for (json, key, message) in cases {
        let c: TrainConfig = serde_json::from_str(json).expect(json);
        let (k, m) = c.problem().unwrap_or_else(|| panic!("{json} was accepted"));
        assert_eq!(k, key, "{json}");
        assert!(m.starts_with(message), "{json}: {m}");
    }
    // NaN passes no range: every check is written to refuse it.
    let mut c = TrainConfig::default();
    for set in [
        |c: &mut TrainConfig| c.lr = f64::NAN,
        |c: &mut TrainConfig| c.beta2 = f64::NAN,
        |c: &mut TrainConfig| c.grad_clip = f64::NAN,
    ] {
        set(&mut c);
        assert!(c.problem().is_some());
        c = TrainConfig::default();
    }
    let stop: TrainConfig = serde_json::from_str(r#"{"nonfinite": "stop"}"#).unwrap();
    assert_eq!(stop.nonfinite, NonFinite::Stop);
    assert_eq!(
        stop.identity(),
        TrainConfig::default().identity(),
        "a resumed run may change it"
    );
    let e = serde_json::from_str::<TrainConfig>(r#"{"nonfinite": "ignore"}"#)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ignore") && e.contains("skip") && e.contains("stop"),
        "{e}"
    );
}
