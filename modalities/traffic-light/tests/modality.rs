//! The traffic-light modality through the public registry, as umgen uses it: layout, hand-computed ids,
//! round trips, the nearest-first order and its count, malformed slots, errors, and the marks it draws.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::f64::consts::PI;
use umgen::UmgenConfig;
use umgen::data::LightState;
use umgen::modality::{Mark, Modality, ModalityCatalog, ModalityRegistry, Slot};
use umgen::scene::{Extra, Frame, SceneClip};
use umgen_modality_traffic_light::{KIND, TrafficLight, TrafficLightConfig, colour};

fn catalog() -> ModalityCatalog {
    let mut catalog = umgen::builtin_catalog().unwrap();
    catalog.add(KIND, TrafficLight::factory).unwrap();
    catalog
}

/// A registry of the lights alone, with `settings` under `[modality.lights]`.
fn registry_of(settings: &str) -> umgen::Result<ModalityRegistry> {
    let text =
        format!("[layout]\norder = [\"lights\"]\n[modality.lights]\nkind = \"traffic_light\"\n{settings}");
    UmgenConfig::from_toml_str(&text).unwrap().registry(&catalog())
}

fn lights_only(settings: &str) -> ModalityRegistry {
    registry_of(settings).unwrap()
}

fn frame(heads: &[[f32; 4]]) -> Frame {
    let mut f = Frame::default();
    f.extras.insert("signals".into(), Extra::F32(heads.concat()));
    f
}

fn clip(mut frames: Vec<Frame>) -> SceneClip {
    for (i, f) in frames.iter_mut().enumerate() {
        f.time = i as f64 * 0.5;
    }
    SceneClip::new("c", 0.5, frames).unwrap()
}

#[test]
fn a_fifth_block_follows_the_paper_layout() {
    let text = std::fs::read_to_string("../../configs/paper.toml").unwrap();
    let base = UmgenConfig::from_toml_str(&text)
        .unwrap()
        .registry(&catalog())
        .unwrap();
    let mut config = UmgenConfig::from_toml_str(&text).unwrap();
    config.layout.order.push("lights".into());
    let table = "kind = \"traffic_light\"\ncount = 6";
    config
        .modality
        .insert("lights".into(), toml::from_str(table).unwrap());
    let registry = config.registry(&catalog()).unwrap();
    let (base, layout) = (base.layout().unwrap(), registry.layout().unwrap());
    assert_eq!(base.len(), 2251);
    assert_eq!(layout.len(), 2251 + 6 * 4 + 2);
    // The built-in blocks do not move; the new block follows them.
    for (a, b) in base.segments().iter().zip(layout.segments()) {
        assert_eq!(a, b);
    }
    let s = layout.segment("lights").unwrap();
    assert_eq!(
        (s.start_pos, s.offset, s.tokens, s.end_pos),
        (Some(2251), 2252, 24, Some(2276))
    );
    // 128 value bins, 4 states, the pad; start and end ids after them.
    assert_eq!((s.vocab_size, s.start_id, s.end_id), (133, 133, 134));
    assert_eq!(s.kind, KIND);
    assert_eq!(layout.position(2253).unwrap().slot, Slot::Content(1));
    assert_eq!(layout.allowed_ids(2253), Some(0..133));
    assert_ne!(layout.fingerprint(), base.fingerprint());
}

#[test]
fn ids_are_the_bins_nearest_first_then_pads() {
    let registry = lights_only("count = 3\n");
    // Farther head first in the frame: the modality orders by distance.
    let heads = [[-30.5, 20.0, -1.5, 3.0], [10.2, -3.7, 1.6, 1.0]];
    let rows = registry.tokenize_clip(&clip(vec![frame(&heads)])).unwrap();
    // 1 m bins over [-64, 64]: x 10.2 → 74, y -3.7 → 60; heading 1.6 → ⌊(1.6 + π) / (2π / 128)⌋ = 96;
    // red → 128 + 1. Then x -30.5 → 33, y 20 → 84, heading -1.5 → 33, green → 131; the third slot pads.
    assert_eq!(
        rows[0],
        [133, 74, 60, 96, 129, 33, 84, 33, 131, 132, 132, 132, 132, 134]
    );
    let mut decoded = Frame::default();
    assert_eq!(registry.detokenize(&rows[0], &mut decoded).unwrap().malformed, 0);
    let Some(Extra::F32(v)) = decoded.extras.get("signals") else {
        panic!("decoding writes the heads back")
    };
    let want = [
        10.5,
        -3.5,
        96.5 * PI / 64.0 - PI,
        1.0,
        -30.5,
        20.5,
        33.5 * PI / 64.0 - PI,
        3.0,
    ];
    assert_eq!(v.len(), want.len());
    for (a, b) in v.iter().zip(want) {
        assert!((f64::from(*a) - b).abs() < 1e-5, "{v:?} against {want:?}");
    }
}

#[test]
fn random_heads_round_trip_within_half_a_bin() {
    let registry = lights_only("count = 8\nbins = 256\n");
    let mut state = 0x9e37_79b9_u32;
    let mut next = move || {
        // xorshift: deterministic heads without a dependency.
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        f64::from(state) / f64::from(u32::MAX)
    };
    let frames: Vec<Frame> = (0..40)
        .map(|i| {
            let heads: Vec<[f32; 4]> = (0..i % 9)
                .map(|_| {
                    let x = (next() * 120.0 - 60.0) as f32;
                    let y = (next() * 120.0 - 60.0) as f32;
                    let h = (next() * 2.0 * PI - PI) as f32;
                    [x, y, h, (next() * 3.99).floor() as f32]
                })
                .collect();
            frame(&heads)
        })
        .collect();
    let rows = registry.tokenize_clip(&clip(frames.clone())).unwrap();
    for (row, f) in rows.iter().zip(&frames) {
        let mut decoded = Frame::default();
        assert_eq!(registry.detokenize(row, &mut decoded).unwrap().malformed, 0);
        let (Some(Extra::F32(want)), Some(Extra::F32(got))) =
            (f.extras.get("signals"), decoded.extras.get("signals"))
        else {
            panic!("both frames hold heads")
        };
        let mut want: Vec<&[f32]> = want.chunks(4).collect();
        want.sort_by(|a, b| a[0].hypot(a[1]).total_cmp(&b[0].hypot(b[1])));
        assert_eq!(got.len(), want.len() * 4);
        for (g, w) in got.chunks(4).zip(want) {
            assert!((g[0] - w[0]).abs() <= 0.25 + 1e-4 && (g[1] - w[1]).abs() <= 0.25 + 1e-4);
            let dh = umgen::scene::wrap_angle(f64::from(g[2] - w[2])).abs();
            assert!(dh <= PI / 256.0 + 1e-4, "{g:?} {w:?}");
            assert_eq!(g[3], w[3]);
        }
    }
}

#[test]
fn heads_beyond_the_count_are_the_farthest_and_are_counted() {
    let m = TrafficLight::new(
        "lights",
        TrafficLightConfig {
            count: 2,
            ..Default::default()
        },
    )
    .unwrap();
    let heads = [
        [40.0, 0.0, 0.0, 1.0],
        [5.0, 0.0, 0.0, 2.0],
        [0.0, -20.0, 0.0, 3.0],
        [60.0, 60.0, 0.0, 0.0],
    ];
    let ids = m.tokenize(&clip(vec![frame(&heads)]), 0).unwrap();
    // The 5 m (yellow) and 20 m (green) heads.
    assert_eq!((ids[3], ids[7]), (130, 131));
    let beyond = m
        .clamp_report()
        .into_iter()
        .find(|c| c.field == "heads beyond count")
        .unwrap();
    assert_eq!(beyond.above, 2);
    // A value out of range is clamped and counted, not refused.
    m.tokenize(&clip(vec![frame(&[[70.0, 0.0, 0.0, 1.0]])]), 0)
        .unwrap();
    let x = m.clamp_report().into_iter().find(|c| c.field == "x").unwrap();
    assert_eq!((x.below, x.above), (0, 1));
}

#[test]
fn a_slot_mixing_states_and_values_is_malformed_and_skipped() {
    let registry = lights_only("count = 3\n");
    // Slot 0 a valid head, slot 1 a state id where x belongs, slot 2 half pad.
    let row = [133, 74, 60, 96, 129, 130, 84, 32, 131, 132, 132, 5, 132, 134];
    let mut decoded = Frame::default();
    assert_eq!(registry.detokenize(&row, &mut decoded).unwrap().malformed, 2);
    let Some(Extra::F32(v)) = decoded.extras.get("signals") else {
        panic!("the valid head is written")
    };
    assert_eq!(v.len(), 4);
    assert_eq!(v[3], 1.0);
}

#[test]
fn bad_input_is_refused_naming_the_modality_and_frame() {
    let registry = lights_only("count = 2\n");
    let err = |f: Frame| {
        registry
            .tokenize_clip(&clip(vec![Frame::default(), f]))
            .unwrap_err()
            .to_string()
    };
    // The first frame lacks the key already.
    let e = err(frame(&[]));
    assert!(
        e.contains("`lights`") && e.contains("extras[\"signals\"]") && e.contains("--tls"),
        "{e}"
    );
    let registry_ok = |f: Frame| {
        registry
            .tokenize_clip(&clip(vec![frame(&[]), f]))
            .unwrap_err()
            .to_string()
    };
    let e = registry_ok(frame(&[[1.0, 2.0, 0.0, 7.0]]));
    assert!(e.contains("frame 1") && e.contains("state code 7"), "{e}");
    let e = registry_ok(frame(&[[1.0, 2.0, 0.0, 1.5]]));
    assert!(e.contains("state code 1.5"), "{e}");
    let mut odd = Frame::default();
    odd.extras.insert("signals".into(), Extra::F32(vec![1.0; 6]));
    let e = registry_ok(odd);
    assert!(e.contains("6 values are not groups of 4"), "{e}");
    let mut bytes = Frame::default();
    bytes.extras.insert("signals".into(), Extra::U8(vec![1]));
    assert!(registry_ok(bytes).contains("must be real values"));
    let e = registry_ok(frame(&[[f32::NAN, 2.0, 0.0, 1.0]]));
    assert!(e.contains("lights") && e.to_lowercase().contains("x"), "{e}");
    // Config errors name the key.
    let config = |s: &str| registry_of(s).unwrap_err().to_string();
    assert!(config("colour = 1\n").contains("modality.lights.colour"));
    assert!(config("count = 0\n").contains("modality.lights.count"));
    assert!(config("x = [5.0, -5.0]\n").contains("modality.lights.x"));
    assert!(config("bins = 1\n").contains("modality.lights.x"));
}

#[test]
fn each_head_is_marked_in_its_states_colour_at_its_stop_line() {
    let m = TrafficLight::new("lights", TrafficLightConfig::default()).unwrap();
    let marks = m.marks(&frame(&[
        [12.0, -4.0, 0.0, 1.0],
        [3.0, 8.0, PI as f32 / 2.0, 3.0],
    ]));
    assert_eq!(marks.len(), 4);
    let Mark::Line {
        from, to, colour: c, ..
    } = marks[0]
    else {
        panic!("a bar first")
    };
    assert_eq!(c, colour(LightState::Red));
    // Across the lane (heading 0: along y), centred on the head.
    assert!((from[0] - 12.0).abs() < 1e-9 && (to[0] - 12.0).abs() < 1e-9);
    assert!(((from[1] + to[1]) / 2.0 + 4.0).abs() < 1e-9 && (from[1] - to[1]).abs() > 2.0);
    let Mark::Dot { at, colour: c, .. } = marks[3] else {
        panic!("then a dot")
    };
    assert_eq!(c, colour(LightState::Green));
    // Behind the stop line, where the traffic comes from (heading +y: smaller y).
    assert!((at[0] - 3.0).abs() < 1e-6 && at[1] < 8.0);
    // A frame without heads draws nothing.
    assert!(m.marks(&Frame::default()).is_empty());
}
