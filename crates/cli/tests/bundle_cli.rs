//! Export, generation and evaluation end to end on the tiny fixture: a bundle that outside readers load
//! and that refuses damage; rollouts whose tokens stay in their vocabularies, that follow ego and agent
//! control and repeat with their seed; `umgen eval` on them.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

mod common;
use common::{ok, python_check, umgen};

use std::path::{Path, PathBuf};
use umgen::data::Dataset;
use umgen_tests::run_fixture::Fixture;

#[test]
fn export_writes_a_bundle_that_opens_and_refuses_damage() {
    let fx = Fixture::new().unwrap();
    let cfg = fx.config("e", 2).unwrap();
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
    for (dir, dtype) in [(&f32_dir, "F32"), (&bf16_dir, "BF16")] {
        let args = [
            dir.as_os_str(),
            dtype.as_ref(),
            "time".as_ref(),
            "oar_heads.heads.0.weight".as_ref(),
        ];
        python_check("check_bundle.py", &args);
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
    // The same scenes as a dataset on the context clip's network: ego poses as in scenes.json.
    let clip0 = &ds.clips()[0];
    let network = ds
        .index()
        .logs
        .iter()
        .find(|l| l.id == clip0.log)
        .unwrap()
        .network
        .clone();
    let data = Dataset::open(&g1.join("dataset")).unwrap();
    assert_eq!(data.clips().len(), 2);
    for (k, clip) in scenes.as_array().unwrap().iter().enumerate() {
        let read = data.read_clip(k).unwrap();
        let want = clip["frames"].as_array().unwrap();
        assert_eq!(read.frames.len(), want.len());
        assert_eq!(
            read.network.as_ref().map(|n| n.id.as_str()),
            Some(network.as_str()),
            "the context clip's network"
        );
        for (f, w) in read.frames.iter().zip(want) {
            let d = (f.ego.x - w["ego"]["x"].as_f64().unwrap()).abs()
                + (f.ego.heading - w["ego"]["heading"].as_f64().unwrap()).abs();
            assert!(d < 1e-3, "scene {k}: ego differs by {d}");
        }
    }

    // `umgen viz` draws any generated scene, context frames included.
    let gif = fx.dir.path().join("scene1.gif");
    let log = ok(umgen(&[
        "viz",
        "--generated",
        g1.to_str().unwrap(),
        "--scene",
        "1",
        "--out",
        gif.to_str().unwrap(),
    ]));
    assert!(
        gif.exists() && log.contains("2 context + 4 generated frames"),
        "{log}"
    );
    let out = umgen(&["viz", "--generated", g1.to_str().unwrap(), "--scene", "2"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("scenes 0..2"));
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
    // `umgen eval` on the rollout with a placed agent: an L2 row per generated frame, rates in [0, 1], an MMD per attribute group.
    let split = ds.clips()[0].split.clone();
    ok(umgen(&[
        "eval",
        "--generated",
        g4.to_str().unwrap(),
        "--reference",
        fx.data.to_str().unwrap(),
        "--split",
        &split,
        "--stride",
        "1",
    ]));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(g4.join("eval/report.json")).unwrap()).unwrap();
    let l2 = report["l2"].as_array().unwrap();
    assert_eq!(l2.len(), 4, "{report}");
    for r in l2 {
        for k in ["ego_model", "ego_constant_velocity"] {
            assert!(r[k].as_f64().unwrap() >= 0.0, "{k}: {r}");
        }
    }
    // The real rate exists (the fixture has cars); the generated one exists when the model drew agents.
    assert!(
        report["collision_rate"]["real"]
            .as_f64()
            .is_some_and(|v| (0.0..=1.0).contains(&v)),
        "{report}"
    );
    let g = &report["collision_rate"]["generated"];
    assert!(
        g.is_null() || g.as_f64().is_some_and(|v| (0.0..=1.0).contains(&v)),
        "{report}"
    );
    for g in ["position", "heading", "size", "velocity"] {
        assert!(report["mmd"][g].as_f64().is_some(), "{g}: {report}");
    }
    assert!(g4.join("eval/report.md").exists() && g4.join("eval/l2.png").exists());
    // The targets: a rollout of the model's own ego on too few clips for the bar, and the collision
    // target's verdict as the horizon's own rates give it.
    let targets = report["targets"].as_array().unwrap();
    assert_eq!(targets[0]["target"], "rollout", "{report}");
    assert_eq!(targets[0]["met"], false, "one clip is fewer than 64");
    let collision = targets.iter().find(|t| t["target"] == "collision rate").unwrap();
    let rates = |side: &serde_json::Value| side["collision_rate"].as_f64();
    let horizon = &report["horizon"];
    let expected = match (rates(&horizon["real"]), rates(&horizon["whole"]["generated"])) {
        (Some(r), Some(g)) => serde_json::json!(g <= 1.25 * r),
        _ => serde_json::Value::Null,
    };
    assert_eq!(collision["met"], expected, "{collision}");
    let md = std::fs::read_to_string(g4.join("eval/report.md")).unwrap();
    assert!(
        md.contains("## Against the targets") && md.contains("| collision rate |"),
        "{md}"
    );

    let json =
        |p: PathBuf| -> serde_json::Value { serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap() };
    let g3 = generate(&bf16_dir, "gen3", "4");
    assert_ne!(
        std::fs::read(g1.join("tokens.json")).unwrap(),
        std::fs::read(g3.join("tokens.json")).unwrap()
    );

    // A time limit that has passed after the first frame: that frame is written, and the metadata says 1.
    let cut = fx.dir.path().join("gen-cut");
    let out = umgen(&[
        "generate",
        "--bundle",
        bf16_dir.to_str().unwrap(),
        "--from-scratch",
        "--frames",
        "3",
        "--time-limit",
        "0.000001",
        "--top-k-of",
        "agent=5",
        "--top-p-of",
        "agent=0.8",
        "--speculate",
        "4",
        "--out",
        cut.to_str().unwrap(),
    ]);
    let log = ok(out);
    assert!(log.contains("1 of 3 frame(s) generated"), "{log}");
    let meta = json(cut.join("meta.json"));
    assert_eq!(meta["frames"], 1);
    assert_eq!(meta["speculate"], 4);
    // The CPU draws on the host whatever --draw says.
    assert_eq!(meta["draw"], "host");
    // Per-modality top-k and top-p are recorded.
    assert_eq!(meta["sampling"]["agent"]["top_k"], 5);
    assert_eq!(meta["sampling"]["map"]["top_k"], 16);
    assert_eq!(meta["sampling"]["agent"]["top_p"], 0.8);
    assert_eq!(meta["sampling"]["map"]["top_p"], 1.0);
    // Per-modality settings naming no modality, or a nucleus outside (0, 1], are refused by name.
    for (flag, value, named) in [
        ("--top-k-of", "lidar=5", "`lidar`"),
        ("--top-p-of", "agent=1.5", "`agent=1.5`"),
    ] {
        let bad = fx.dir.path().join("gen-bad");
        let out = umgen(&[
            "generate",
            "--bundle",
            bf16_dir.to_str().unwrap(),
            "--from-scratch",
            flag,
            value,
            "--out",
            bad.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(named),
            "{flag} {value}: {err}"
        );
    }
    assert_eq!(
        json(cut.join("tokens.json"))["scenes"][0]
            .as_array()
            .unwrap()
            .len(),
        1
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
