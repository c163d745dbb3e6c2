//! Settings of the traffic-light modality (`[modality.<name>]`).

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use umgen::modality::{ModalityError, Result, ScalarBins};

/// Tokens per head: x, y, heading and the state.
pub const SLOT: usize = 4;

/// Names of the three value tokens of a slot, in order; the fourth token is the state.
pub const VALUE_FIELDS: [&str; 3] = ["x", "y", "heading"];

/// Settings of the traffic-light modality.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrafficLightConfig {
    /// Heads per frame (nearest to the ego first); a frame with fewer fills the rest with empty slots.
    pub count: usize,
    /// Bins per value (x, y, heading); the four state ids follow them.
    pub bins: u32,
    /// Range of x (m, ego frame, forward).
    pub x: [f64; 2],
    /// Range of y (m, ego frame, left).
    pub y: [f64; 2],
    /// The [`Frame::extras`](umgen::scene::Frame::extras) key the heads are read from and decoded into:
    /// x, y, heading and state code per head, as `umgen data sumo --tls` writes them.
    pub key: String,
}

impl Default for TrafficLightConfig {
    fn default() -> Self {
        Self {
            count: 8,
            bins: 128,
            x: [-64.0, 64.0],
            y: [-64.0, 64.0],
            key: umgen::data::SIGNALS_KEY.to_string(),
        }
    }
}

impl TrafficLightConfig {
    /// Token id of a state code (0 off, 1 red, 2 yellow, 3 green).
    pub fn state_id(&self, code: u8) -> u32 {
        self.bins + u32::from(code)
    }

    /// Token id of an empty slot.
    pub fn pad_id(&self) -> u32 {
        self.bins + 4
    }

    /// Content ids: value bins, four states, the pad.
    pub fn vocab_size(&self) -> u32 {
        self.bins + 5
    }

    /// The bins of x, y and heading, checked; errors name the key under `modality.<name>`.
    pub fn fields(&self, name: &str) -> Result<Vec<(String, ScalarBins)>> {
        if self.count == 0 {
            return Err(ModalityError::Config {
                key: format!("modality.{name}.count"),
                message: "must be at least 1".into(),
            });
        }
        let ranges = [self.x, self.y, [-PI, PI]];
        VALUE_FIELDS
            .iter()
            .zip(ranges)
            .map(|(field, [lo, hi])| {
                let key = format!("modality.{name}.{field}");
                Ok((field.to_string(), ScalarBins::new(&key, lo, hi, self.bins)?))
            })
            .collect()
    }
}
