//! Settings of the agent modality.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use umgen_modality::{Result, ScalarBins};
use umgen_scene::AgentCategory;

/// Tokens per agent slot: ten values and the category.
pub const ATTRIBUTES: usize = 11;

/// Names of the ten value tokens of a slot, in order; the eleventh token is the category.
pub const VALUE_FIELDS: [&str; 10] = [
    "x", "y", "z", "vx", "vy", "vz", "heading", "length", "width", "height",
];

/// Settings of the agent modality (`[modality.<name>]`). Defaults are the paper's (supplementary Table).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct AgentConfig {
    /// Bins per value; category ids follow them.
    pub bins: u32,
    /// Slots per frame.
    pub max_agents: usize,
    /// Range of x (m).
    pub x: [f64; 2],
    /// Range of y (m).
    pub y: [f64; 2],
    /// Range of z (m).
    pub z: [f64; 2],
    /// Range of vx (m/s).
    pub vx: [f64; 2],
    /// Range of vy (m/s).
    pub vy: [f64; 2],
    /// Range of vz (m/s).
    pub vz: [f64; 2],
    /// Range of the heading (rad); headings are wrapped to [-π, π) first.
    pub heading: [f64; 2],
    /// Range of the length (m).
    pub length: [f64; 2],
    /// Range of the width (m).
    pub width: [f64; 2],
    /// Range of the height (m).
    pub height: [f64; 2],
}

impl Default for AgentConfig {
    fn default() -> Self {
        Self {
            bins: 1024,
            max_agents: 64,
            x: [-64.0, 64.0],
            y: [-64.0, 64.0],
            z: [-5.0, 5.0],
            vx: [-20.0, 20.0],
            vy: [-20.0, 20.0],
            vz: [-0.3, 0.3],
            heading: [-PI, PI],
            length: [0.0, 15.0],
            width: [0.0, 4.0],
            height: [0.0, 5.0],
        }
    }
}

impl AgentConfig {
    /// Token id of a category.
    pub fn category_id(&self, c: AgentCategory) -> u32 {
        self.bins + c.index() as u32
    }

    /// Token id of an empty slot.
    pub fn pad_id(&self) -> u32 {
        self.bins + 3
    }

    /// Ranges in [`VALUE_FIELDS`] order.
    pub fn ranges(&self) -> [[f64; 2]; 10] {
        [
            self.x,
            self.y,
            self.z,
            self.vx,
            self.vy,
            self.vz,
            self.heading,
            self.length,
            self.width,
            self.height,
        ]
    }

    /// Named bins for the ten values; errors name `modality.<name>.<field>`.
    pub(crate) fn fields(&self, name: &str) -> Result<Vec<(String, ScalarBins)>> {
        VALUE_FIELDS
            .iter()
            .zip(self.ranges())
            .map(|(f, [lo, hi])| {
                Ok((
                    f.to_string(),
                    ScalarBins::new(&format!("modality.{name}.{f}"), lo, hi, self.bins)?,
                ))
            })
            .collect()
    }
}
