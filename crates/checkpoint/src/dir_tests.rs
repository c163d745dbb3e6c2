//! Checkpoint directories: saving, pruning, verifying, falling back, and what a resumed run moves aside
//! or removes.

use super::*;

#[test]
fn save_keeps_the_last_k_and_points_latest_at_the_newest() {
    let dir = tempfile::tempdir().unwrap();
    let c = CheckpointDir::new(dir.path(), 2);
    for step in [10, 20, 30] {
        c.save(
            "test",
            step,
            serde_json::json!({"step": step}),
            &[("a.bin", &[step as u8; 4])],
        )
        .unwrap();
    }
    let steps: Vec<u64> = c.list().unwrap().into_iter().map(|(s, _)| s).collect();
    assert_eq!(steps, vec![20, 30]);
    assert_eq!(
        std::fs::read_to_string(dir.path().join(LATEST)).unwrap(),
        "step-000000030"
    );
    let l = c.load_latest().unwrap().unwrap();
    assert_eq!((l.manifest.step, l.file("a.bin").unwrap()), (30, &[30u8; 4][..]));
    assert!(
        l.file("b.bin")
            .unwrap_err()
            .to_string()
            .contains("no file `b.bin`")
    );
}

#[test]
fn a_damaged_newest_checkpoint_falls_back_to_the_previous() {
    let dir = tempfile::tempdir().unwrap();
    let c = CheckpointDir::new(dir.path(), 3);
    c.save("test", 1, serde_json::Value::Null, &[("w", b"one")])
        .unwrap();
    let newest = c
        .save("test", 2, serde_json::Value::Null, &[("w", b"two")])
        .unwrap();
    std::fs::write(newest.join("w"), b"tw0").unwrap();
    let err = load(&newest).unwrap_err().to_string();
    assert!(
        err.contains("step-000000002") && err.contains("checksum"),
        "{err}"
    );
    let l = c.load_latest().unwrap().unwrap();
    assert_eq!(l.manifest.step, 1);
    // An interrupted save (no manifest) is skipped the same way.
    std::fs::create_dir_all(dir.path().join("step-000000003")).unwrap();
    assert_eq!(c.load_latest().unwrap().unwrap().manifest.step, 1);
    assert!(
        CheckpointDir::new(dir.path().join("none"), 1)
            .load_latest()
            .unwrap()
            .is_none()
    );
}

#[test]
fn none_readable_is_an_error_naming_each_and_the_highest_good_step_wins() {
    let dir = tempfile::tempdir().unwrap();
    let c = CheckpointDir::new(dir.path(), 5);
    let one = c
        .save("test", 1, serde_json::Value::Null, &[("w", b"one")])
        .unwrap();
    let two = c
        .save("test", 2, serde_json::Value::Null, &[("w", b"two")])
        .unwrap();
    // `latest` naming an older checkpoint (a kill between the rename and `latest`'s) does not hide step 2.
    std::fs::write(dir.path().join(LATEST), "step-000000001").unwrap();
    assert_eq!(c.load_latest().unwrap().unwrap().manifest.step, 2);
    std::fs::write(one.join("w"), b"0ne").unwrap();
    std::fs::remove_file(two.join(MANIFEST)).unwrap();
    let err = c.load_latest().unwrap_err().to_string();
    assert!(
        err.contains("2 checkpoint(s) and none is readable")
            && err.contains("step-000000002: no readable manifest")
            && err.contains("step-000000001: file `w` fails its checksum"),
        "{err}"
    );
    assert!(
        err.find("step-000000002").unwrap() < err.find("step-000000001").unwrap(),
        "newest first: {err}"
    );
}

#[test]
fn newer_damaged_checkpoints_are_set_aside_and_never_pruned_for() {
    let dir = tempfile::tempdir().unwrap();
    let c = CheckpointDir::new(dir.path(), 1);
    for step in [10, 20] {
        c.save("test", step, serde_json::Value::Null, &[("w", &[step as u8])])
            .unwrap();
    }
    // keep = 1 pruned step 10; make 20 the only one and damage it, then write 10 again as a good one.
    std::fs::write(dir.path().join("step-000000020/w"), [0u8]).unwrap();
    let err = c.load_latest().unwrap_err().to_string();
    assert!(err.contains("none is readable"), "{err}");
    let moved = c.set_aside_newer(10).unwrap();
    assert_eq!(moved, [dir.path().join("step-000000020.damaged")]);
    assert_eq!(
        std::fs::read(moved[0].join("w")).unwrap(),
        [0u8],
        "moved, not rewritten"
    );
    c.save("test", 15, serde_json::Value::Null, &[("w", b"ok")])
        .unwrap();
    // A second damaged step 20 goes beside the first; the list holds the good one alone.
    std::fs::create_dir_all(dir.path().join("step-000000020")).unwrap();
    assert_eq!(
        c.set_aside_newer(15).unwrap(),
        [dir.path().join("step-000000020.damaged-2")]
    );
    let steps: Vec<u64> = c.list().unwrap().into_iter().map(|(s, _)| s).collect();
    assert_eq!(steps, [15]);
    // Saving over an existing step moves that one aside as well.
    std::fs::create_dir_all(dir.path().join("step-000000016")).unwrap();
    c.save("test", 16, serde_json::Value::Null, &[("w", b"new")])
        .unwrap();
    assert!(dir.path().join("step-000000016.damaged").is_dir());
}

#[test]
fn interrupted_saves_are_removed_with_their_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let c = CheckpointDir::new(dir.path(), 2);
    assert!(c.remove_stale_temporaries().unwrap().is_empty());
    c.save("test", 1, serde_json::Value::Null, &[("w", b"one")])
        .unwrap();
    let tmp = dir.path().join(".step-000000002.tmp-77");
    std::fs::create_dir_all(&tmp).unwrap();
    std::fs::write(tmp.join("model.safetensors"), [1u8; 300]).unwrap();
    std::fs::write(tmp.join("optimizer.bin"), [1u8; 50]).unwrap();
    std::fs::write(dir.path().join(".latest.tmp-77"), b"step-000000002").unwrap();
    let removed = c.remove_stale_temporaries().unwrap();
    assert_eq!(
        removed,
        [(dir.path().join(".latest.tmp-77"), 14), (tmp.clone(), 350)]
    );
    assert!(!tmp.exists() && dir.path().join("step-000000001").exists() && dir.path().join(LATEST).exists());
}
