//! Traffic-light states imported with a SUMO trace (`--tls`): where the heads stand, their states at each
//! frame, and the files refused by name.

use super::{fcd_text, fixture, write};
use umgen_data::sumo::{ImportOptions, import, parse_heads};
use umgen_data::{Dataset, SIGNALS_KEY, ViewOptions};
use umgen_scene::Extra;

/// Light B's states: red from the start, green for link 0 from t = 1.0 (link 1 turns amber), then the
/// trace's steps every 0.5 s.
const TLS: &str = r#"<?xml version="1.0"?>
<tlsStates>
    <tlsState time="0.00" id="B" programID="0" phase="0" state="rr"/>
    <tlsState time="1.00" id="B" programID="0" phase="1" state="Gy"/>
    <tlsState time="2.00" id="B" programID="0" phase="1" state="Gy"/>
</tlsStates>
"#;

fn options(dir: &std::path::Path, tls: &str) -> ImportOptions {
    let fcd = write(dir, "run.fcd.xml", &fcd_text(6, "AB_0"));
    let mut o = ImportOptions::new(fixture("tiny.net.xml"), fcd, dir.join("ds"));
    (o.min_frames, o.clip_frames) = (3, 4);
    o.tls = Some(write(dir, "run.tls.xml", tls));
    o
}

#[test]
fn heads_stand_at_the_stop_line_of_the_lane_they_control() {
    let heads = parse_heads(&fixture("tiny.net.xml")).unwrap();
    assert_eq!(heads.len(), 2);
    let h = &heads[0];
    assert_eq!((h.tl.as_str(), h.link), ("B", 0));
    assert!(
        (h.x - 100.0).abs() < 1e-9 && (h.y + 4.8).abs() < 1e-9 && h.heading.abs() < 1e-9,
        "{h:?}"
    );
    assert!((heads[1].y + 1.6).abs() < 1e-9);
}

#[test]
fn signalled_pedestrian_crossings_are_not_heads() {
    // The light also signals the crossing, from the walking area (SUMO: a link from an internal edge).
    let net = std::fs::read_to_string(fixture("tiny.net.xml")).unwrap().replace(
        "    <junction id=\"B\"",
        "    <connection from=\":B_w0\" to=\":B_c0\" fromLane=\"0\" toLane=\"0\" tl=\"B\" linkIndex=\"2\" \
         dir=\"s\" state=\"o\"/>\n    <junction id=\"B\"",
    );
    let dir = tempfile::tempdir().unwrap();
    let heads = parse_heads(&write(dir.path(), "crossing.net.xml", &net)).unwrap();
    assert_eq!(heads, parse_heads(&fixture("tiny.net.xml")).unwrap());
    assert!(net.contains("linkIndex=\"2\""));
}

#[test]
fn frames_list_the_heads_in_view_with_the_state_of_their_step() {
    let dir = tempfile::tempdir().unwrap();
    let report = import(&options(dir.path(), TLS)).unwrap();
    assert_eq!(report.signal_heads, 2);
    // The heads stand 65–80 m ahead: outside the default ±64 m view, inside ±100 m.
    let near = Dataset::open(&dir.path().join("ds")).unwrap();
    let ego = near.find_clip("run/ego:0").unwrap();
    let clip = near.read_window(ego, 0, 4, 1).unwrap();
    let none = Extra::F32(Vec::new());
    assert!(
        clip.frames
            .iter()
            .all(|f| f.extras.get(SIGNALS_KEY) == Some(&none))
    );
    let ds = Dataset::open(&dir.path().join("ds"))
        .unwrap()
        .with_options(ViewOptions { agent_range: 100.0 });
    let clip = ds.read_window(ego, 0, 4, 1).unwrap();
    // Frame i is at t = 0.5 i; the ego's centre at x = 20 + 5 i on y = -4.8, heading east.
    let expected_states = [[1.0, 1.0], [1.0, 1.0], [3.0, 2.0], [3.0, 2.0]];
    for (i, f) in clip.frames.iter().enumerate() {
        let Some(Extra::F32(v)) = f.extras.get(SIGNALS_KEY) else {
            panic!("frame {i} has no signals: {:?}", f.extras)
        };
        assert_eq!(v.len(), 8, "frame {i}: {v:?}");
        let ahead = 80.0 - 5.0 * i as f32;
        // Link 0 on the ego's own lane, straight ahead; link 1 one lane (3.2 m) to the left, farther.
        assert!(
            (v[0] - ahead).abs() < 1e-3 && v[1].abs() < 1e-3 && v[2].abs() < 1e-6,
            "frame {i}: {v:?}"
        );
        assert!(
            (v[4] - ahead).abs() < 1e-3 && (v[5] - 3.2).abs() < 1e-3,
            "frame {i}: {v:?}"
        );
        assert_eq!([v[3], v[7]], expected_states[i], "frame {i}");
    }
    // A dataset without signals has no such extra.
    let plain = tempfile::tempdir().unwrap();
    let mut o = options(plain.path(), TLS);
    o.tls = None;
    import(&o).unwrap();
    let ds = Dataset::open(&plain.path().join("ds")).unwrap();
    let clip = ds.read_window(0, 0, 3, 1).unwrap();
    assert!(clip.frames.iter().all(|f| f.extras.is_empty()));
}

#[test]
fn states_the_network_cannot_hold_are_refused_by_name_and_nothing_is_written() {
    let cases = [
        (
            TLS.replace(
                "id=\"B\" programID=\"0\" phase=\"1\"",
                "id=\"C\" programID=\"0\" phase=\"1\"",
            ),
            "`C`",
        ),
        (TLS.replace("state=\"rr\"", "state=\"r\""), "no link 1"),
        (TLS.replace("state=\"rr\"", "state=\"rx\""), "`x`"),
        ("<fcd-export/>".to_string(), "tlsStates"),
    ];
    for (text, needle) in cases {
        let dir = tempfile::tempdir().unwrap();
        let e = import(&options(dir.path(), &text)).unwrap_err().to_string();
        assert!(e.contains("run.tls.xml") && e.contains(needle), "{needle}: {e}");
        assert!(
            !dir.path().join("ds").exists(),
            "{needle}: the dataset was written"
        );
    }
}
