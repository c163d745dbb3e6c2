//! [`TrafficLight`]: the [`Modality`] implementation.

use crate::config::{SLOT, TrafficLightConfig};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use umgen::data::LightState;
use umgen::modality::{
    ClampCount, DecodeReport, Discretizer, Mark, Modality, ModalityError, ModalitySpec, Result, Stops,
    parse_settings,
};
use umgen::scene::{Extra, Frame, SceneClip};

/// The kind name used in configs (`kind = "traffic_light"`).
pub const KIND: &str = "traffic_light";

/// One head as a frame holds it: x, y (m), heading (rad) in the ego's frame, and its state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Head {
    /// Position (m, ego frame).
    pub x: f64,
    /// Position (m, ego frame).
    pub y: f64,
    /// Direction of travel at the stop line (rad, ego frame).
    pub heading: f64,
    /// The signal's state.
    pub state: LightState,
}

/// The traffic-light modality: the `count` heads nearest to the ego, four tokens each.
#[derive(Debug)]
pub struct TrafficLight {
    spec: ModalitySpec,
    config: TrafficLightConfig,
    bins: Discretizer,
    farther: AtomicU64,
}

impl TrafficLight {
    /// A traffic-light modality called `name`.
    pub fn new(name: &str, config: TrafficLightConfig) -> Result<Self> {
        let fields = config.fields(name)?;
        let bins = |i: usize| (i, fields[i].1);
        // Every head is a stop point while red, released where another head at the same stop line (the
        // same x and y bins: the end of one lane) shows green or yellow, as `crossings` reads a line.
        let state = |s: LightState| config.state_id(s as u8);
        let stops = Stops {
            slot: SLOT,
            values: config.bins,
            fields: [bins(0), bins(1), bins(2)],
            state: 3,
            stop: vec![state(LightState::Red)],
            go: vec![state(LightState::Yellow), state(LightState::Green)],
        };
        let spec = ModalitySpec::new(name, KIND, config.vocab_size(), config.count * SLOT)
            .with_pad(config.pad_id())
            .with_ordinal(config.bins)
            .with_stops(stops);
        spec.validate()?;
        Ok(Self {
            spec,
            bins: Discretizer::new(name, fields),
            config,
            farther: AtomicU64::new(0),
        })
    }

    /// Builds the modality from its config table: the factory to register under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }

    /// The settings in use.
    pub fn config(&self) -> &TrafficLightConfig {
        &self.config
    }

    /// The heads `frame` holds under the configured key, in stored order; `t` is the frame's index for
    /// errors. A frame without the key is an error: its dataset was imported without `--tls`.
    pub fn heads(&self, frame: &Frame, t: usize) -> Result<Vec<Head>> {
        let name = &self.spec.name;
        let key = &self.config.key;
        let bad = |message: String| ModalityError::Tokenizer {
            modality: name.clone(),
            message: format!("frame {t}: extras[\"{key}\"]: {message}"),
        };
        let values = match frame.extras.get(key) {
            Some(Extra::F32(v)) => v,
            Some(_) => return Err(bad("must be real values (x, y, heading, state per head)".into())),
            None => {
                return Err(ModalityError::MissingInput {
                    modality: name.clone(),
                    frame: t,
                    what: format!("extras[\"{key}\"] (import the data with `umgen data sumo --tls`)"),
                });
            }
        };
        if values.len() % SLOT != 0 {
            return Err(bad(format!("{} values are not groups of {SLOT}", values.len())));
        }
        values
            .chunks_exact(SLOT)
            .map(|h| {
                let state = h[3];
                if !(0.0..=3.0).contains(&state) || state.fract() != 0.0 {
                    return Err(bad(format!("state code {state} is not 0, 1, 2 or 3")));
                }
                Ok(Head {
                    x: f64::from(h[0]),
                    y: f64::from(h[1]),
                    heading: f64::from(h[2]),
                    state: LightState::from_code(state as u8),
                })
            })
            .collect()
    }

    fn encode(&self, heads: &[Head]) -> Result<Vec<u32>> {
        let mut near: Vec<&Head> = heads.iter().collect();
        // Nearest first (the importer's order already; decoded frames may come in any order).
        near.sort_by(|a, b| a.x.hypot(a.y).total_cmp(&b.x.hypot(b.y)));
        if near.len() > self.config.count {
            let beyond = (near.len() - self.config.count) as u64;
            self.farther.fetch_add(beyond, Ordering::Relaxed);
        }
        let mut ids = vec![self.config.pad_id(); self.spec.tokens_per_frame];
        for (slot, h) in ids.chunks_exact_mut(SLOT).zip(near) {
            let heading = umgen::scene::wrap_angle(h.heading);
            for (i, v) in [h.x, h.y, heading].into_iter().enumerate() {
                slot[i] = self.bins.encode(i, v)?;
            }
            slot[3] = self.config.state_id(h.state as u8);
        }
        Ok(ids)
    }

    /// The head one slot's ids stand for: `Ok(None)` for an empty slot, `Err(())` for a malformed one.
    fn decode_slot(&self, slot: &[u32]) -> std::result::Result<Option<Head>, ()> {
        let pad = self.config.pad_id();
        if slot.iter().all(|&id| id == pad) {
            return Ok(None);
        }
        let value = |i: usize| self.bins.decode(i, slot[i]).ok_or(());
        let code = slot[3]
            .checked_sub(self.config.bins)
            .filter(|&c| c < 4)
            .ok_or(())?;
        Ok(Some(Head {
            x: value(0)?,
            y: value(1)?,
            heading: value(2)?,
            state: LightState::from_code(code as u8),
        }))
    }
}

impl Modality for TrafficLight {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::json!({
            "count": self.config.count,
            "bins": self.config.bins,
            "x": self.config.x,
            "y": self.config.y,
            "key": self.config.key,
            "states": ["off", "red", "yellow", "green"],
        })
    }

    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        self.encode(&self.heads(clip.frame(t)?, t)?)
    }

    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        self.spec.check_frame_ids(ids)?;
        let mut report = DecodeReport::default();
        let mut values = Vec::with_capacity(ids.len());
        for slot in ids.chunks_exact(SLOT) {
            match self.decode_slot(slot) {
                Ok(Some(h)) => {
                    values.extend([h.x as f32, h.y as f32, h.heading as f32, f32::from(h.state as u8)])
                }
                Ok(None) => {}
                Err(()) => report.malformed += 1,
            }
        }
        frame.extras.insert(self.config.key.clone(), Extra::F32(values));
        Ok(report)
    }

    fn clamp_report(&self) -> Vec<ClampCount> {
        let mut report = self.bins.clamp_report();
        report.push(ClampCount {
            field: "heads beyond count".into(),
            below: 0,
            above: self.farther.load(Ordering::Relaxed),
        });
        report
    }

    /// Each head as a bar across its lane at the stop line, in the state's colour, with a dot on the
    /// side the traffic comes from.
    fn marks(&self, frame: &Frame) -> Vec<Mark> {
        // A frame without heads draws nothing; its tokenization reports the problem.
        let Ok(heads) = self.heads(frame, 0) else {
            return Vec::new();
        };
        heads
            .iter()
            .flat_map(|h| {
                let colour = colour(h.state);
                let (s, c) = h.heading.sin_cos();
                // Half a lane across the direction of travel.
                let (ax, ay) = (-s * 1.6, c * 1.6);
                [
                    Mark::Line {
                        from: [h.x - ax, h.y - ay],
                        to: [h.x + ax, h.y + ay],
                        width: 0.8,
                        colour,
                    },
                    Mark::Dot {
                        at: [h.x - c * 1.2, h.y - s * 1.2],
                        radius: 0.7,
                        colour,
                    },
                ]
            })
            .collect()
    }
}

/// The colour a state is drawn in.
pub fn colour(state: LightState) -> [u8; 3] {
    match state {
        LightState::Red => [235, 45, 45],
        LightState::Yellow => [245, 200, 40],
        LightState::Green => [60, 220, 100],
        LightState::Off => [150, 150, 150],
    }
}
