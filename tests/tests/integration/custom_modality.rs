//! A fifth modality defined outside the built-in crates joins the frame purely through the trait.

use rand::{Rng, SeedableRng, rngs::StdRng};
use umgen::UmgenConfig;
use umgen::modality::{ModalityCatalog, Slot};
use umgen::scene::{Agent, AgentCategory, EgoAction, EgoPose, Extra, Frame, SceneClip};
use umgen_tests::traffic_lights::{self, TrafficLights};

fn catalog() -> ModalityCatalog {
    let mut catalog = umgen::builtin_catalog().unwrap();
    catalog.add(traffic_lights::KIND, TrafficLights::factory).unwrap();
    catalog
}

fn paper_with_lights(count: usize) -> UmgenConfig {
    let mut config =
        UmgenConfig::from_toml_str(&std::fs::read_to_string("../configs/paper.toml").unwrap()).unwrap();
    config.layout.order.push("lights".into());
    let table = format!("kind = \"traffic_lights\"\ncount = {count}");
    config
        .modality
        .insert("lights".into(), toml::from_str(&table).unwrap());
    config
}

#[test]
fn fifth_modality_extends_the_paper_layout() {
    let base =
        UmgenConfig::from_toml_str(&std::fs::read_to_string("../configs/paper.toml").unwrap()).unwrap();
    let base = base.registry(&catalog()).unwrap();
    let base = base.layout().unwrap();
    let registry = paper_with_lights(6).registry(&catalog()).unwrap();
    let layout = registry.layout().unwrap();
    assert_eq!(base.len(), 2251);
    assert_eq!(layout.len(), 2251 + 6 + 2);
    // The built-in blocks do not move; the new block follows them.
    for (a, b) in base.segments().iter().zip(layout.segments()) {
        assert_eq!(a, b);
    }
    let lights = layout.segment("lights").unwrap();
    assert_eq!(
        (lights.start_pos, lights.offset, lights.tokens, lights.end_pos),
        (Some(2251), 2252, 6, Some(2258))
    );
    assert_eq!(
        (
            lights.vocab_size,
            lights.start_id,
            lights.end_id,
            lights.kind.as_str()
        ),
        (4, 4, 5, "traffic_lights")
    );
    assert_eq!(layout.position(2253).unwrap().slot, Slot::Content(1));
    assert_eq!(layout.allowed_ids(2253), Some(0..4));
    assert_ne!(layout.fingerprint(), base.fingerprint());
}

fn random_clip(rng: &mut StdRng, frames: usize, lights: usize) -> SceneClip {
    let mut pose = EgoPose::default();
    let frames = (0..frames)
        .map(|t| {
            let action = EgoAction::new(
                rng.random_range(0.0..10.0),
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.25..0.25),
            );
            pose = pose.advance(&action, 0.5);
            let agents = (0..rng.random_range(0..6))
                .map(|i| Agent {
                    track_id: i,
                    category: AgentCategory::ALL[i as usize % 3],
                    x: rng.random_range(-60.0..60.0),
                    y: rng.random_range(-60.0..60.0),
                    z: 0.0,
                    vx: rng.random_range(-10.0..10.0),
                    vy: rng.random_range(-10.0..10.0),
                    vz: 0.0,
                    heading: rng.random_range(-3.0..3.0),
                    length: 4.0,
                    width: 2.0,
                    height: 1.5,
                })
                .collect();
            let states: Vec<u8> = (0..rng.random_range(0..=lights))
                .map(|_| rng.random_range(0..4))
                .collect();
            let mut f = Frame {
                time: t as f64 * 0.5,
                ego: pose,
                action,
                agents,
                ..Frame::default()
            };
            f.extras.insert("lights".into(), Extra::U8(states));
            f
        })
        .collect();
    SceneClip::new("random", 0.5, frames).unwrap()
}

#[test]
fn fifth_modality_round_trips_through_the_registry() {
    let config = UmgenConfig::from_toml_str(
        "[layout]\norder = [\"ego\", \"agent\", \"lights\"]\n[modality.agent]\nmax_agents = 8\n\
         [modality.lights]\nkind = \"traffic_lights\"\ncount = 3\n",
    )
    .unwrap();
    let registry = config.registry(&catalog()).unwrap();
    let layout = registry.layout().unwrap();
    let mut rng = StdRng::seed_from_u64(5);
    let clip = random_clip(&mut rng, 12, 3);
    let rows = registry.tokenize_clip(&clip).unwrap();
    assert_eq!(rows.len(), 12);
    for (row, frame) in rows.iter().zip(&clip.frames) {
        layout.check_row(row).unwrap();
        let mut decoded = Frame::default();
        assert_eq!(registry.detokenize(row, &mut decoded).unwrap().malformed, 0);
        let Some(Extra::U8(want)) = frame.extras.get("lights") else {
            panic!("fixture has lights")
        };
        let mut want = want.clone();
        want.resize(3, 0);
        assert_eq!(decoded.extras.get("lights"), Some(&Extra::U8(want)));
        assert!((decoded.action.dx - frame.action.dx).abs() <= 10.0 / 2048.0 + 1e-12);
        assert_eq!(decoded.agents.len(), frame.agents.len());
    }
}

#[test]
fn fifth_modality_errors_name_it() {
    let config = UmgenConfig::from_toml_str(
        "[layout]\norder = [\"lights\"]\n[modality.lights]\nkind = \"traffic_lights\"\ncount = 2\n",
    )
    .unwrap();
    let registry = config.registry(&catalog()).unwrap();
    let mut frame = Frame::default();
    frame.extras.insert("lights".into(), Extra::U8(vec![1, 9]));
    let clip = SceneClip::new("c", 0.5, vec![frame]).unwrap();
    let err = registry.tokenize_clip(&clip).unwrap_err().to_string();
    assert!(err.contains("`lights`") && err.contains("state 9"), "{err}");
    let clip = SceneClip::new("c", 0.5, vec![Frame::default()]).unwrap();
    let err = registry.tokenize_clip(&clip).unwrap_err().to_string();
    assert!(
        err.contains("`lights`") && err.contains("extras[\"lights\"]"),
        "{err}"
    );
    let bad = UmgenConfig::from_toml_str(
        "[layout]\norder = [\"lights\"]\n[modality.lights]\nkind = \"traffic_lights\"\ncolor = 1\n",
    )
    .unwrap();
    let err = bad.registry(&catalog()).unwrap_err().to_string();
    assert!(err.contains("modality.lights.color"), "{err}");
}
