//! An example modality outside the built-in crates: the states of the `count` traffic lights nearest to
//! the ego, one token per light (0 off or unknown, 1 red, 2 yellow, 3 green).
//!
//! It reads `frame.extras["<name>"]` (bytes, at most `count`; missing lights are "off") and writes the
//! same key back when decoding. `docs/adding-a-modality.md` walks through it.

use serde::{Deserialize, Serialize};
use std::sync::Arc;
use umgen::modality::{DecodeReport, Modality, ModalityError, ModalitySpec, Result, parse_settings};
use umgen::scene::{Extra, Frame, SceneClip};

/// The kind name used in configs.
pub const KIND: &str = "traffic_lights";

/// Light states; the token id is the state's index.
pub const STATES: [&str; 4] = ["off", "red", "yellow", "green"];

/// Settings (`[modality.<name>]`).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrafficLightConfig {
    /// Lights per frame (tokens per frame).
    pub count: usize,
}

impl Default for TrafficLightConfig {
    fn default() -> Self {
        Self { count: 4 }
    }
}

/// The traffic-light modality.
#[derive(Debug)]
pub struct TrafficLights {
    spec: ModalitySpec,
    config: TrafficLightConfig,
}

impl TrafficLights {
    /// A traffic-light modality called `name`.
    pub fn new(name: &str, config: TrafficLightConfig) -> Result<Self> {
        let spec = ModalitySpec::new(name, KIND, STATES.len() as u32, config.count);
        spec.validate()?;
        Ok(Self { spec, config })
    }

    /// The factory to add to a catalog under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }
}

impl Modality for TrafficLights {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::json!({ "count": self.config.count, "states": STATES })
    }

    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        let name = &self.spec.name;
        let missing = || ModalityError::MissingInput {
            modality: name.clone(),
            frame: t,
            what: format!("extras[\"{name}\"]"),
        };
        let states = match clip.frame(t)?.extras.get(name).ok_or_else(missing)? {
            Extra::U8(states) => states,
            _ => {
                return Err(ModalityError::Tokenizer {
                    modality: name.clone(),
                    message: format!("frame {t}: extras must be bytes"),
                });
            }
        };
        if states.len() > self.config.count {
            return Err(ModalityError::TokenCount {
                modality: name.clone(),
                expected: self.config.count,
                actual: states.len(),
            });
        }
        let mut ids = vec![0; self.config.count];
        for (out, &s) in ids.iter_mut().zip(states) {
            if usize::from(s) >= STATES.len() {
                return Err(ModalityError::Tokenizer {
                    modality: name.clone(),
                    message: format!("frame {t}: light state {s} is not 0..=3"),
                });
            }
            *out = u32::from(s);
        }
        Ok(ids)
    }

    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        if ids.len() != self.config.count {
            return Err(ModalityError::TokenCount {
                modality: self.spec.name.clone(),
                expected: self.config.count,
                actual: ids.len(),
            });
        }
        let mut report = DecodeReport::default();
        let states = ids
            .iter()
            .map(|&id| {
                u8::try_from(id)
                    .ok()
                    .filter(|&s| usize::from(s) < STATES.len())
                    .unwrap_or_else(|| {
                        report.malformed += 1;
                        0
                    })
            })
            .collect();
        frame.extras.insert(self.spec.name.clone(), Extra::U8(states));
        Ok(report)
    }
}
