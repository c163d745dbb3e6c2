//! The traffic-agent modality (paper supplementary B.2.3): `max_agents` slots of 11 tokens per frame,
//! `x, y, z, vx, vy, vz, heading, length, width, height, category`, all in the frame's ego coordinates.
//!
//! Values use `bins` uniform bins (ids `0..bins`); the category token is `bins` (vehicle), `bins + 1`
//! (pedestrian) or `bins + 2` (cyclist); an empty slot is 11 pad tokens, id `bins + 3`. With the default
//! 1024 bins that is the paper's 1024–1026 and 1027, and a vocabulary of 1028.
//!
//! Slots are assigned per clip ([`SlotPlan`]): a track keeps one slot in every frame of the clip and is a
//! pad where it is absent. When a clip has more tracks than slots, the tracks that come nearest to the
//! ego are kept; the observations of the others are counted in the `slots` line of the clamp report.

mod config;
mod slots;

pub use config::{ATTRIBUTES, AgentConfig, VALUE_FIELDS};
pub use slots::SlotPlan;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use umgen_modality::{
    ClampCount, DecodeReport, Discretizer, Modality, ModalityError, ModalitySpec, Result, Tracks,
    parse_settings,
};
use umgen_scene::{Agent, AgentCategory, Frame, SceneClip, wrap_angle};

/// The kind name used in configs.
pub const KIND: &str = "agent";

/// The agent modality.
#[derive(Debug)]
pub struct AgentModality {
    spec: ModalitySpec,
    config: AgentConfig,
    bins: Discretizer,
    unslotted: AtomicU64,
}

impl AgentModality {
    /// An agent modality called `name`.
    pub fn new(name: &str, config: AgentConfig) -> Result<Self> {
        let fields = config.fields(name)?;
        if config.max_agents == 0 {
            return Err(ModalityError::Config {
                key: format!("modality.{name}.max_agents"),
                message: "must be at least 1".into(),
            });
        }
        // x, y, vx, vy, heading: what a backbone moves by constant velocity and the ego motion.
        let moved = [0, 1, 3, 4, 6].map(|i| (i, fields[i].1));
        let spec = ModalitySpec::new(name, KIND, config.bins + 4, config.max_agents * ATTRIBUTES)
            .with_pad(config.pad_id())
            .with_ordinal(config.bins)
            .with_tracks(Tracks {
                slot: ATTRIBUTES,
                values: config.bins,
                fields: moved,
            });
        Ok(Self {
            spec,
            config,
            bins: Discretizer::new(name, fields),
            unslotted: AtomicU64::new(0),
        })
    }

    /// Builds the modality from its config table; the factory registered under [`KIND`].
    pub fn factory(name: &str, table: &toml::Table) -> Result<Arc<dyn Modality>> {
        Ok(Arc::new(Self::new(name, parse_settings(name, table)?)?))
    }

    /// The settings in use.
    pub fn config(&self) -> &AgentConfig {
        &self.config
    }

    fn encode_frame(&self, plan: &SlotPlan, frame: &Frame) -> Result<Vec<u32>> {
        let pad = self.config.pad_id();
        let mut ids = vec![pad; self.spec.tokens_per_frame];
        for agent in &frame.agents {
            let Some(slot) = plan.slot(agent.track_id) else {
                self.unslotted.fetch_add(1, Ordering::Relaxed);
                continue;
            };
            let values = [
                agent.x,
                agent.y,
                agent.z,
                agent.vx,
                agent.vy,
                agent.vz,
                wrap_angle(agent.heading),
                agent.length,
                agent.width,
                agent.height,
            ];
            let out = &mut ids[slot * ATTRIBUTES..(slot + 1) * ATTRIBUTES];
            for (i, v) in values.into_iter().enumerate() {
                out[i] = self.bins.encode(i, v)?;
            }
            out[ATTRIBUTES - 1] = self.config.category_id(agent.category);
        }
        Ok(ids)
    }

    /// Decodes one slot's 11 tokens: `Ok(None)` for an empty slot, `Err(())` for a malformed one.
    fn decode_slot(&self, slot: usize, t: &[u32]) -> Result<Option<Agent>, ()> {
        let pad = self.config.pad_id();
        if t.iter().all(|&id| id == pad) {
            return Ok(None);
        }
        let category = AgentCategory::ALL
            .into_iter()
            .find(|&c| self.config.category_id(c) == t[ATTRIBUTES - 1])
            .ok_or(())?;
        let mut v = [0.0; ATTRIBUTES - 1];
        for (i, out) in v.iter_mut().enumerate() {
            *out = self.bins.decode(i, t[i]).ok_or(())?;
        }
        Ok(Some(Agent {
            track_id: slot as u64,
            category,
            x: v[0],
            y: v[1],
            z: v[2],
            vx: v[3],
            vy: v[4],
            vz: v[5],
            heading: v[6],
            length: v[7],
            width: v[8],
            height: v[9],
        }))
    }
}

impl Modality for AgentModality {
    fn spec(&self) -> &ModalitySpec {
        &self.spec
    }

    fn settings(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).unwrap_or(serde_json::Value::Null)
    }

    fn tokenize(&self, clip: &SceneClip, t: usize) -> Result<Vec<u32>> {
        let plan = SlotPlan::new(clip, self.config.max_agents)?;
        self.encode_frame(&plan, clip.frame(t)?)
    }

    fn tokenize_clip(&self, clip: &SceneClip) -> Result<Vec<Vec<u32>>> {
        let plan = SlotPlan::new(clip, self.config.max_agents)?;
        clip.frames.iter().map(|f| self.encode_frame(&plan, f)).collect()
    }

    /// Replaces `frame.agents` with the decoded slots; an agent's track id is its slot index. A slot that
    /// mixes pad and value ids, or has no valid category, is skipped and counted as malformed.
    fn detokenize(&self, ids: &[u32], frame: &mut Frame) -> Result<DecodeReport> {
        self.spec.check_frame_ids(ids)?;
        let mut report = DecodeReport::default();
        frame.agents.clear();
        for (slot, t) in ids.chunks_exact(ATTRIBUTES).enumerate() {
            match self.decode_slot(slot, t) {
                Ok(Some(agent)) => frame.agents.push(agent),
                Ok(None) => {}
                Err(()) => report.malformed += 1,
            }
        }
        Ok(report)
    }

    /// Value clamps per attribute, plus a `slots` line whose `above` counts agent observations that found
    /// no slot because their clip had more tracks than `max_agents`.
    fn clamp_report(&self) -> Vec<ClampCount> {
        let mut report = self.bins.clamp_report();
        report.push(ClampCount {
            field: "slots".into(),
            below: 0,
            above: self.unslotted.load(Ordering::Relaxed),
        });
        report
    }
}
