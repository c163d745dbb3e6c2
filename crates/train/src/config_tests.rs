//! Training settings: kernel choices that leave the run's identity alone, and values no run can use.

use super::*;

#[test]
fn kernel_settings_parse_are_checked_and_resuming_may_change_them() {
    use umgen_ops::kernels::{
        AdamWChoice, AttentionKernel, GeluKernel, KernelStream, LaunchThread, MatmulKernel, NormKernel,
        XentKernel,
    };
    let default = TrainConfig::default();
    let parse = |json: &str| serde_json::from_str::<TrainConfig>(json);
    let all = parse(
        r#"{"kernels": {"matmul": "named", "attention": "fused", "attention_step": 32,
            "attention_block_mib": 256, "recompute": true, "norm": "burn", "gelu": "burn", "xent": "burn",
            "adamw": "burn", "stream": "side", "launch_thread": "caller"}}"#,
    )
    .expect("every kernel choice");
    let k = all.kernels;
    assert_eq!(
        (
            k.matmul,
            k.attention,
            k.norm,
            k.gelu,
            k.xent,
            k.adamw,
            k.stream,
            k.launch_thread
        ),
        (
            MatmulKernel::Named,
            AttentionKernel::Fused,
            NormKernel::Burn,
            GeluKernel::Burn,
            XentKernel::Burn,
            AdamWChoice::Burn,
            KernelStream::Side,
            LaunchThread::Caller
        )
    );
    assert_eq!(
        (k.attention_step, k.attention_block_mib, k.recompute),
        (32, 256, true)
    );
    // The loss runs on the run's kernels.
    assert_eq!(all.loss_options().expect("valid").kernels, k);
    // Kernel choices leave a run's identity alone, so a run may resume under others.
    assert_eq!(default.identity(), all.identity());
    // So does sharding the optimizer state, which steps every parameter to the same bits.
    let sharded = parse(r#"{"shard_optimizer": true}"#).expect("shard_optimizer");
    assert!(sharded.shard_optimizer);
    assert_eq!(default.identity(), sharded.identity());
    // A setting that changes the run still does.
    let lr = parse(r#"{"lr": 0.5}"#).expect("lr");
    assert_ne!(default.identity(), lr.identity());
    // Unknown names are refused, naming the value and what is accepted.
    let e = parse(r#"{"kernels": {"attention": "flash"}}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("flash") && e.contains("flash2"), "{e}");
    let e = parse(r#"{"kernels": {"matmul": "tma"}}"#)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("tma") && e.contains("cublas") && e.contains("named") && e.contains("burn"),
        "{e}"
    );
    // The choices live in their table only.
    let e = parse(r#"{"matmul": "named"}"#).unwrap_err().to_string();
    assert!(e.contains("matmul"), "{e}");
    let e = parse(r#"{"kernels": {"kernel_stream": "side"}}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("kernel_stream"), "{e}");
    // Values no run can use are named with their key.
    let (key, why) = parse(r#"{"kernels": {"attention_step": 48}}"#)
        .expect("parses")
        .problem()
        .expect("48 is not a step");
    assert_eq!(key, "kernels.attention_step");
    assert!(why.contains("48"), "{why}");
    let (key, _) = parse(r#"{"kernels": {"attention_block_mib": 0}}"#)
        .expect("parses")
        .problem()
        .expect("0 MiB");
    assert_eq!(key, "kernels.attention_block_mib");
    let (key, why) = parse(r#"{"kernels": {"flash2_warps": 6}}"#)
        .expect("parses")
        .problem()
        .expect("6 warps");
    assert_eq!(key, "kernels.flash2_warps");
    assert!(why.contains('6'), "{why}");
    let (key, why) = parse(r#"{"kernels": {"attention_backward": "one-pass", "stream": "side"}}"#)
        .expect("parses")
        .problem()
        .expect("one-pass on a side stream");
    assert_eq!(key, "kernels.attention_backward");
    assert!(why.contains("cubecl"), "{why}");
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
        (
            r#"{"kernels": {"attention_step": 48}}"#,
            "kernels.attention_step",
            "attention step 48",
        ),
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

#[test]
fn an_empty_dataset_path_is_none() {
    let data = |json: &str| serde_json::from_str::<TrainConfig>(json).map(|c| c.data);
    assert_eq!(data(r#"{"data": ""}"#).unwrap(), None);
    assert_eq!(data(r#"{}"#).unwrap(), None);
    assert_eq!(
        data(r#"{"data": "data/sumo-more"}"#).unwrap(),
        Some(PathBuf::from("data/sumo-more"))
    );
    assert!(data(r#"{"data": 3}"#).is_err(), "a number is no path");
}
