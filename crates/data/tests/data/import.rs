//! Importing SUMO traces: what lands in the dataset, and what is refused without writing anything.

use super::{fcd_text, fixture, write};
use umgen_data::sumo::{ImportOptions, import};
use umgen_data::{DataError, Dataset, INDEX_FILE};
use umgen_scene::AgentCategory;

fn options(dir: &std::path::Path, fcd: std::path::PathBuf) -> ImportOptions {
    let mut o = ImportOptions::new(fixture("tiny.net.xml"), fcd, dir.join("ds"));
    (o.min_frames, o.clip_frames) = (3, 4);
    o
}

#[test]
fn imported_frames_show_agents_where_sumo_put_them() {
    let dir = tempfile::tempdir().unwrap();
    let fcd = write(dir.path(), "run.fcd.xml", &fcd_text(6, "AB_0"));
    let report = import(&options(dir.path(), fcd)).unwrap();
    // Both cars can be egos; 6 steps make one clip of 4 (the 2 left are under min_frames).
    assert_eq!(
        (
            report.log.as_str(),
            report.network.as_str(),
            report.steps,
            report.tracks,
            report.clips
        ),
        ("run", "tiny", 6, 3, 2)
    );
    let ds = Dataset::open(&dir.path().join("ds")).unwrap();
    assert_eq!(ds.index().frame_interval, 0.5);
    let ego = ds.find_clip("run/ego:0").unwrap();
    let clip = ds.read_window(ego, 1, 3, 1).unwrap();
    assert_eq!(clip.frames.len(), 3);
    let f = &clip.frames[0];
    // Front bumper 10 m ahead of the ego's front bumper: box centres 10 m apart.
    let lead = f
        .agents
        .iter()
        .find(|a| a.category == AgentCategory::Vehicle)
        .unwrap();
    assert!(
        (lead.x - 10.0).abs() < 1e-4 && lead.y.abs() < 1e-4 && lead.heading.abs() < 1e-6,
        "{lead:?}"
    );
    assert!((lead.vx - 10.0).abs() < 1e-4 && (lead.length, lead.width) == (5.0, 1.8));
    // At t = 0.5 the ego's bumper is at x = 27.5, its centre 2.5 m behind; the walker is at (30.5, -7.4).
    assert!((f.ego.x - 25.0).abs() < 1e-4 && (f.ego.y + 4.8).abs() < 1e-4 && f.ego.heading.abs() < 1e-6);
    let walker = f
        .agents
        .iter()
        .find(|a| a.category == AgentCategory::Pedestrian)
        .unwrap();
    assert!(
        (walker.x - 5.5).abs() < 1e-4 && (walker.y + 2.6).abs() < 1e-4,
        "{walker:?}"
    );
    // The first frame's action comes from the step before the window: 10 m/s for 0.5 s.
    assert!((f.action.dx - 5.0).abs() < 1e-4 && f.action.dy.abs() < 1e-4);
    assert_eq!(ds.index().stats.frames, 8);
    assert_eq!(ds.index().stats.categories.get("pedestrian"), Some(&8));
    assert!(clip.network.is_some());
}

#[test]
fn malformed_xml_is_refused_with_file_and_line_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = fcd_text(4, "AB_0");
    let cut = text.find("<vehicle id=\"lead\"").unwrap() + 10;
    text.insert_str(cut, "<<");
    let fcd = write(dir.path(), "bad.fcd.xml", &text);
    match import(&options(dir.path(), fcd.clone())).unwrap_err() {
        DataError::Input { path, line, .. } => assert_eq!((path, line), (fcd, 5)),
        other => panic!("unexpected {other}"),
    }
    assert!(!dir.path().join("ds").exists());
}

#[test]
fn a_trace_from_another_network_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = write(dir.path(), "good.fcd.xml", &fcd_text(4, "AB_0"));
    import(&options(dir.path(), good)).unwrap();
    let index_before = std::fs::read(dir.path().join("ds").join(INDEX_FILE)).unwrap();
    let fcd = write(dir.path(), "other.fcd.xml", &fcd_text(4, "XY_0"));
    let err = import(&options(dir.path(), fcd.clone())).unwrap_err();
    let msg = err.to_string();
    assert!(msg.starts_with(&format!("{}:4:", fcd.display())), "{msg}");
    assert!(
        msg.contains("lane `XY_0`") && msg.contains("does not match the network"),
        "{msg}"
    );
    assert_eq!(
        std::fs::read(dir.path().join("ds").join(INDEX_FILE)).unwrap(),
        index_before
    );
    assert!(!dir.path().join("ds/logs/other.ulog").exists());
}

#[test]
fn unknown_types_and_irregular_steps_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = fcd_text(4, "AB_0").replacen("DEFAULT_PEDTYPE", "alien", 1);
    let fcd = write(dir.path(), "t.fcd.xml", &text);
    let msg = import(&options(dir.path(), fcd)).unwrap_err().to_string();
    assert!(msg.contains("type `alien`") && msg.contains("--types"), "{msg}");
    let text = fcd_text(4, "AB_0").replace("time=\"1.50\"", "time=\"1.70\"");
    let fcd = write(dir.path(), "s.fcd.xml", &text);
    let msg = import(&options(dir.path(), fcd)).unwrap_err().to_string();
    // Line 2 opens the trace; each step takes 5 lines, so step 3 starts on line 18.
    assert!(
        msg.contains("s.fcd.xml:18:") && msg.contains("timestep 1.7"),
        "{msg}"
    );
    let net = write(
        dir.path(),
        "x.net.xml",
        "<net><edge id=\"e\"><lane id=\"e_0\" shape=\"0,0\"/></edge></net>",
    );
    let mut o = options(dir.path(), fixture("tiny.net.xml"));
    o.net = net.clone();
    let msg = import(&o).unwrap_err().to_string();
    assert!(
        msg.starts_with(&format!("{}:1:", net.display())) && msg.contains("two points"),
        "{msg}"
    );
    assert!(!dir.path().join("ds").exists());
}

#[test]
fn logs_and_clips_cannot_collide() {
    let dir = tempfile::tempdir().unwrap();
    let fcd = write(dir.path(), "run.fcd.xml", &fcd_text(6, "AB_0"));
    import(&options(dir.path(), fcd.clone())).unwrap();
    let msg = import(&options(dir.path(), fcd.clone())).unwrap_err().to_string();
    assert!(msg.contains("already has a log `run`"), "{msg}");
    let mut o = options(dir.path(), fcd);
    o.name = Some("run2".into());
    o.split = "test".into();
    assert_eq!(import(&o).unwrap().clips, 2);
    let ds = Dataset::open(&dir.path().join("ds")).unwrap();
    assert_eq!(ds.index().networks.len(), 1, "the same network is shared");
    assert_eq!(ds.windows(3, 1, Some("test")).len(), 4);
    assert_eq!(ds.windows(3, 1, None).len(), 8);
    assert_eq!(ds.windows(3, 2, None).len(), 0);
}
