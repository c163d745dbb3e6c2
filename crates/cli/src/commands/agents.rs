//! The agent modality's slots as `umgen generate` steers them: control-file states encoded into tokens,
//! whole-slot groups with the new-agent rule, and keep-alive positions.

use anyhow::Context;
use umgen::Bundle;
use umgen::generate::{Control, TokenGroups};
use umgen::modality::{Modality, ModalityRegistry, ScalarBins, Segment};
use umgen::modality_agent::{ATTRIBUTES, AgentConfig, VALUE_FIELDS};
use umgen::scene::AgentCategory;

/// Placed tokens and id limits of one frame.
pub type Placement = (Vec<(usize, u32)>, Vec<(usize, u32)>);

/// Where the agent slots sit in a frame and how their values are binned.
#[derive(Debug)]
pub struct AgentSlots {
    offset: usize,
    slots: usize,
    cfg: AgentConfig,
    /// Bins of the ten values, in [`VALUE_FIELDS`] order.
    bins: Vec<ScalarBins>,
}

/// The registry's modality of `kind` and its segment of the frame layout; `None` when the layout has none.
pub fn modality_of_kind<'a>(
    registry: &'a ModalityRegistry,
    kind: &str,
) -> anyhow::Result<Option<(&'a dyn Modality, &'a Segment)>> {
    let layout = registry.layout()?;
    let found = registry
        .modalities()
        .iter()
        .zip(layout.segments())
        .find(|(_, seg)| seg.kind == kind);
    Ok(found.map(|(m, seg)| (m.as_ref(), seg)))
}

/// The registry's agent modality and its segment of the frame layout; `None` when the layout has none.
pub fn agent_modality(registry: &ModalityRegistry) -> anyhow::Result<Option<(&dyn Modality, &Segment)>> {
    modality_of_kind(registry, umgen::modality_agent::KIND)
}

impl AgentSlots {
    /// The model's agent modality (`None` without one), from the bundle's config.
    pub fn of(bundle: &Bundle, registry: &ModalityRegistry) -> anyhow::Result<Option<Self>> {
        let Some((name, offset, cfg)) = umgen::agent_segment(registry, &bundle.config)? else {
            return Ok(None);
        };
        let bins = VALUE_FIELDS
            .iter()
            .zip(cfg.ranges())
            .map(|(field, [lo, hi])| ScalarBins::new(&format!("modality.{name}.{field}"), lo, hi, cfg.bins))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Some(Self {
            offset,
            slots: cfg.max_agents,
            cfg,
            bins,
        }))
    }

    /// A position (ego frame) at the centres of its `x` and `y` bins, and whether either was outside its
    /// range (then at the nearest edge bin).
    pub fn round_xy(&self, p: [f64; 2]) -> ([f64; 2], bool) {
        let mut clamped = false;
        let out = [0, 1].map(|f| {
            let (id, clamp) = self.bins[f].encode(p[f]);
            clamped |= clamp.is_some();
            self.bins[f].decode(id).unwrap_or(p[f])
        });
        (out, clamped)
    }

    /// The vehicle category's token id.
    pub fn vehicle_id(&self) -> u32 {
        self.cfg.category_id(AgentCategory::Vehicle)
    }

    /// Agent slots per frame.
    pub fn slots(&self) -> usize {
        self.slots
    }

    /// Tokens placed at generated frame `k`: each value the control file sets and the slot's category; the
    /// slot's other attributes are drawn from the value bins only (never pad or a category).
    pub fn placement(&self, control: &Control, k: usize) -> anyhow::Result<Placement> {
        let (mut out, mut below) = (Vec::new(), Vec::new());
        for (i, a) in control.agents_at(k).enumerate() {
            anyhow::ensure!(
                a.slot < self.slots,
                "agent[{i}].slot = {}: this model has slots 0..{}",
                a.slot,
                self.slots
            );
            let base = self.offset + a.slot * ATTRIBUTES;
            for (name, v) in a.values() {
                let f = VALUE_FIELDS
                    .iter()
                    .position(|x| *x == name)
                    .context("unknown agent field")?;
                let (id, clamp) = self.bins[f].encode(v);
                if clamp.is_some() {
                    tracing::warn!(
                        "frame {k}: agent slot {} {name} = {v} is outside [{}, {}], clamped",
                        a.slot,
                        self.bins[f].lo,
                        self.bins[f].hi
                    );
                }
                out.push((base + f, id));
            }
            // `Control::validate` refused unknown names (`umgen generate` validates first); no name is a vehicle.
            let category = a
                .category
                .as_deref()
                .and_then(AgentCategory::from_name)
                .unwrap_or(AgentCategory::Vehicle);
            out.push((base + ATTRIBUTES - 1, self.cfg.category_id(category)));
            below.extend((0..ATTRIBUTES - 1).map(|f| (base + f, self.cfg.bins)));
        }
        Ok((out, below))
    }

    /// The slots as token groups ([`umgen::agent_groups`]).
    pub fn groups(&self) -> TokenGroups {
        umgen::agent_groups(self.offset, self.slots, &self.cfg)
    }

    /// Every slot position whose token was not pad in a scene's newest frame: a pad drawn there is redrawn
    /// from the TAR head, so agents leave the scene when the TAR says so, not on one OAR draw.
    pub fn keep(&self, history: &[Vec<Vec<u32>>]) -> Vec<(usize, u32, Vec<bool>)> {
        let pad = self.cfg.pad_id();
        (self.offset..self.offset + self.slots * ATTRIBUTES)
            .filter_map(|p| {
                let alive: Vec<bool> = history
                    .iter()
                    .map(|h| h.last().is_some_and(|f| f.get(p).is_some_and(|&id| id != pad)))
                    .collect();
                alive.iter().any(|&x| x).then_some((p, pad, alive))
            })
            .collect()
    }
}
