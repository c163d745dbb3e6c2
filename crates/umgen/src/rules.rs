//! How generation decodes a model's frames beyond its logits: the history window, the default draw
//! settings and the agent slots' token groups. `umgen generate` applies them, and `umgen export` writes
//! them into the manifest's `generation` section for runners outside umgen (docs/export-format.md).

use crate::config::UmgenConfig;
use crate::error::Result;
use umgen_generate::{GroupBoxes, Sampling, TokenGroups};
use umgen_modality::ModalityRegistry;
use umgen_modality_agent::{ATTRIBUTES, AgentConfig};
use umgen_scene::AgentCategory;

/// The paper's longest history window.
const PAPER_WINDOW: usize = 20;

/// The frames of history the TAR sees by default: the longest history the model was trained on
/// (`train.frames`; its time embeddings past that never received a gradient), at most the paper's 20 and
/// `backbone.max_frames`.
pub fn history_window(config: &UmgenConfig) -> usize {
    PAPER_WINDOW
        .min(config.backbone.max_frames)
        .min(config.train.frames.max(1))
}

/// Length and width (m) of the ego's box in the new-agent rule (the official code's ego vehicle), and in
/// `umgen eval`'s count of agents overlapping the ego.
pub const EGO_BOX_M: [f64; 2] = [5.176, 2.297];

/// The agent slots from content position `offset` (`slots` of them) as token groups: each comes out either
/// empty (all pad) or as values and a category, never a mix that decodes to nothing; new agents follow
/// the official rule (the ego box, l 5.176 m × w 2.297 m, first; no overlaps; at most 30 other boxes),
/// tested against every old agent of the frame, not only those in the slots before them
/// ([`GroupBoxes::whole_frame`]; docs/decisions/019-new-agents-against-the-whole-frame.md).
pub fn agent_groups(offset: usize, slots: usize, cfg: &AgentConfig) -> TokenGroups {
    let ids: Vec<u32> = AgentCategory::ALL.iter().map(|c| cfg.category_id(*c)).collect();
    let (lo, hi) = (
        ids.iter().min().copied().unwrap_or(0),
        ids.iter().max().copied().unwrap_or(0),
    );
    let ranges = cfg.ranges();
    TokenGroups {
        first: offset,
        size: ATTRIBUTES,
        count: slots,
        pad: cfg.pad_id(),
        values: cfg.bins,
        last: lo..hi + 1,
        // x, y, heading, length and width.
        boxes: Some(GroupBoxes {
            fields: [0, 1, 6, 7, 8].map(|i| (i, ranges[i][0], ranges[i][1], cfg.bins)),
            ego: EGO_BOX_M,
            max_boxes: 31,
            whole_frame: true,
        }),
    }
}

/// The agent modality of `registry` (a segment of kind `agent`): its name, content offset and settings;
/// `None` when the layout has none.
pub fn agent_segment(
    registry: &ModalityRegistry,
    config: &UmgenConfig,
) -> Result<Option<(String, usize, AgentConfig)>> {
    let layout = registry.layout()?;
    let Some(seg) = layout
        .segments()
        .iter()
        .find(|s| s.kind == umgen_modality_agent::KIND)
    else {
        return Ok(None);
    };
    let table = config.modality.get(&seg.modality).cloned().unwrap_or_default();
    let cfg: AgentConfig = umgen_modality::parse_settings(&seg.modality, &table)?;
    Ok(Some((seg.modality.clone(), seg.offset, cfg)))
}

/// The agent slots of `registry`'s layout as token groups ([`agent_groups`]); `None` without an agent
/// modality.
pub fn agent_slot_groups(registry: &ModalityRegistry, config: &UmgenConfig) -> Result<Option<TokenGroups>> {
    Ok(agent_segment(registry, config)?.map(|(_, offset, cfg)| agent_groups(offset, cfg.max_agents, &cfg)))
}

/// The manifest's `generation` section: `window`, the default `sampling` per modality name, and the
/// token `groups` (each with `keep`: a slot filled in a scene's newest frame redraws a pad from the TAR
/// head; and `boxes`: the new-agent rule).
pub fn generation_manifest(registry: &ModalityRegistry, config: &UmgenConfig) -> Result<serde_json::Value> {
    let layout = registry.layout()?;
    let sampling: serde_json::Map<String, serde_json::Value> = layout
        .segments()
        .iter()
        .map(|s| (s.modality.clone(), sampling_json(&Sampling::default())))
        .collect();
    let groups: Vec<serde_json::Value> = agent_slot_groups(registry, config)?
        .map(|g| {
            serde_json::json!({
                "first": g.first, "size": g.size, "count": g.count, "pad": g.pad, "values": g.values,
                "last": [g.last.start, g.last.end], "keep": true,
                "boxes": g.boxes.map(|b| serde_json::json!({
                    "fields": b.fields.map(|(i, lo, hi, bins)| serde_json::json!([i, lo, hi, bins])),
                    "ego": b.ego, "max_boxes": b.max_boxes, "whole_frame": b.whole_frame,
                })),
            })
        })
        .into_iter()
        .collect();
    Ok(serde_json::json!({
        "window": history_window(config),
        "sampling": sampling,
        "groups": groups,
    }))
}

fn sampling_json(s: &Sampling) -> serde_json::Value {
    serde_json::json!({"top_k": s.top_k, "top_p": s.top_p, "temperature": s.temperature})
}
