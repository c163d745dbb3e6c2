//! The log format: round trips and damaged files, each error naming the file.

use umgen_data::{DataError, Log, LogShard, State, Track};
use umgen_scene::AgentCategory;

fn log(steps: usize) -> Log {
    let tracks = (0..3)
        .map(|i| Track {
            name: format!("t{i}"),
            category: AgentCategory::Vehicle,
            class: "passenger".into(),
            length: 4.5,
            width: 1.8,
            height: 1.5,
        })
        .collect();
    let steps = (0..steps)
        .map(|s| {
            (0..3u32)
                .filter(|t| !(s + *t as usize).is_multiple_of(4))
                .map(|t| State {
                    track: t,
                    x: s as f32,
                    y: t as f32,
                    heading: 0.1,
                    speed: 2.0,
                })
                .collect()
        })
        .collect();
    Log {
        tracks,
        t0: 60.0,
        dt: 0.5,
        steps,
    }
}

#[test]
fn logs_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.ulog");
    let original = log(100);
    original.write(&p).unwrap();
    let shard = LogShard::open(&p).unwrap();
    assert_eq!(shard.read_all().unwrap(), original);
    let s = shard.step(77).unwrap();
    assert_eq!(s.states(), &original.steps[77][..]);
    assert_eq!(
        s.get(2).map(|x| x.y),
        original.steps[77].iter().find(|x| x.track == 2).map(|x| x.y)
    );
    assert!(shard.step(100).is_err());
}

fn corrupt_at(offset_from_end: u64) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("b.ulog");
    log(100).write(&p).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    let i = bytes.len() - offset_from_end as usize;
    bytes[i] ^= 0x40;
    std::fs::write(&p, bytes).unwrap();
    (dir, p)
}

#[test]
fn a_flipped_byte_is_caught_in_its_chunk() {
    let (_dir, p) = corrupt_at(7);
    let shard = LogShard::open(&p).unwrap();
    assert!(shard.step(0).is_ok(), "chunks before the damage still read");
    match shard.step(99).unwrap_err() {
        DataError::Corrupt { path, reason } => {
            assert_eq!(path, p);
            assert!(reason.contains("checksum"), "{reason}");
        }
        other => panic!("unexpected {other}"),
    }
}

#[test]
fn truncated_and_foreign_files_are_refused_at_open() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.ulog");
    log(10).write(&p).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 20]).unwrap();
    let msg = LogShard::open(&p).unwrap_err().to_string();
    assert!(msg.contains("c.ulog") && msg.contains("truncated"), "{msg}");
    std::fs::write(&p, &bytes[..10]).unwrap();
    assert!(LogShard::open(&p).unwrap_err().to_string().contains("c.ulog"));
    std::fs::write(&p, b"not a log at all, just text").unwrap();
    assert!(LogShard::open(&p).unwrap_err().to_string().contains("bad magic"));
    let mut header = bytes.clone();
    header[20] ^= 1;
    std::fs::write(&p, header).unwrap();
    assert!(
        LogShard::open(&p)
            .unwrap_err()
            .to_string()
            .contains("header checksum")
    );
}
