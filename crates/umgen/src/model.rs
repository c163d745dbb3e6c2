//! The backbone's view of a registry.

use crate::error::{Result, UmgenError};
use umgen_backbone::{
    ActionSpec, AlignSpec, BackboneConfig, BackboneSpec, FollowSpec, SegmentSpec, StopSpec, TrackSpec,
};
use umgen_modality::{FrameLayout, ModalityError, ModalityRegistry};

fn config_error(key: &str, message: String) -> UmgenError {
    UmgenError::Modality(ModalityError::Config {
        key: key.into(),
        message,
    })
}

/// The frame as the backbone sees it: segments with vocabularies and codebooks, the action segment and
/// its bins (`backbone.action`), the map grid AMA moves (`backbone.align`), the tracked slots
/// (`backbone.track`).
pub fn backbone_spec(registry: &ModalityRegistry, cfg: &BackboneConfig) -> Result<BackboneSpec> {
    let layout = registry.layout()?;
    let segments = layout
        .segments()
        .iter()
        .zip(registry.modalities())
        .map(|(s, m)| SegmentSpec {
            label: s.modality.clone(),
            block_start: s.block_start,
            block_len: s.block_end - s.block_start,
            offset: s.offset,
            tokens: s.tokens,
            vocab: s.vocab_size as usize,
            embed_vocab: s.embed_vocab as usize,
            ordinal: m.spec().ordinal as usize,
            codebook: m
                .codebook()
                .filter(|c| c.entries() == s.vocab_size as usize)
                .map(|c| (c.dim(), c.weights().to_vec())),
        })
        .collect();
    let index = |key: &str, name: &str| {
        layout
            .segments()
            .iter()
            .position(|s| s.modality == name)
            .ok_or_else(|| config_error(key, format!("no modality `{name}` in layout.order")))
    };
    // An empty name turns the part off (TOML has no null).
    let action = match cfg.action.as_deref().filter(|s| !s.is_empty()) {
        None => None,
        Some(name) => {
            let i = index("backbone.action", name)?;
            let b = &layout.segments()[i].bins;
            if b.len() < 3 {
                return Err(config_error(
                    "backbone.action",
                    format!("modality `{name}` does not declare binned dx, dy, dθ tokens"),
                ));
            }
            Some(ActionSpec {
                segment: i,
                bins: [0, 1, 2].map(|k| (b[k].lo, b[k].hi, b[k].bins)),
            })
        }
    };
    let align = match cfg.align.as_deref().filter(|s| !s.is_empty()) {
        None => None,
        Some(name) => {
            let i = index("backbone.align", name)?;
            match layout.segments()[i].grid {
                Some(g) if g.cell_m.is_some() => Some(AlignSpec {
                    segment: i,
                    rows: g.rows,
                    cols: g.cols,
                    cell_m: g.cell_m.unwrap_or(1.0),
                }),
                _ => {
                    return Err(config_error(
                        "backbone.align",
                        format!("modality `{name}` is not a metric bird's-eye grid"),
                    ));
                }
            }
        }
    };
    if align.is_some() && action.is_none() {
        return Err(config_error(
            "backbone.align",
            "AMA needs `backbone.action` to know how the ego moves".into(),
        ));
    }
    let track = match cfg.track.as_deref().filter(|s| !s.is_empty()) {
        None if cfg.track_accel => {
            return Err(config_error(
                "backbone.track_accel",
                "moving tracked slots by their acceleration needs `backbone.track`".into(),
            ));
        }
        None if cfg.track_follow => {
            return Err(config_error(
                "backbone.track_follow",
                "braking tracked slots for what is ahead needs `backbone.track`".into(),
            ));
        }
        None if stops_name(cfg).is_some() => {
            return Err(config_error(
                "backbone.track_stops",
                "stopping tracked slots at stop points needs `backbone.track`".into(),
            ));
        }
        None => None,
        Some(name) => {
            let i = index("backbone.track", name)?;
            let Some(k) = layout.segments()[i].tracks else {
                return Err(config_error(
                    "backbone.track",
                    format!("modality `{name}` does not declare slots of tracked objects"),
                ));
            };
            if action.is_none() {
                return Err(config_error(
                    "backbone.track",
                    "moving the tracked slots needs `backbone.action` to know how the ego moves".into(),
                ));
            }
            if !(cfg.step_s.is_finite() && cfg.step_s > 0.0) {
                return Err(config_error(
                    "backbone.step_s",
                    format!("{} s is not a positive time between frames", cfg.step_s),
                ));
            }
            Some(TrackSpec {
                segment: i,
                slot: k.slot,
                values: k.values,
                fields: k.fields.map(|(j, b)| (j, (b.lo, b.hi, b.bins))),
                step_s: cfg.step_s,
                pad: layout.segments()[i].pad_id,
                accel: cfg.track_accel,
                follow: cfg.track_follow.then(FollowSpec::default),
                stops: stop_spec(cfg, layout, &index)?,
            })
        }
    };
    let spec = BackboneSpec {
        n: layout.len(),
        segments,
        action,
        align,
        track,
    };
    spec.validate(cfg)
        .map_err(|e| config_error("backbone", e.to_string()))?;
    Ok(spec)
}

// A modality's stop ids fit the backbone's, which fit the kernels' arrays.
const _: () = assert!(umgen_modality::Stops::MAX_IDS == umgen_backbone::STOP_IDS);

/// `backbone.track_stops`, when set to a name.
fn stops_name(cfg: &BackboneConfig) -> Option<&str> {
    cfg.track_stops.as_deref().filter(|s| !s.is_empty())
}

/// The stop points of `backbone.track_stops`: the named modality's declared stop slots, for the follow
/// rule to brake at; `index` finds a modality's segment.
fn stop_spec(
    cfg: &BackboneConfig,
    layout: &FrameLayout,
    index: &dyn Fn(&str, &str) -> Result<usize>,
) -> Result<Option<StopSpec>> {
    const KEY: &str = "backbone.track_stops";
    let Some(name) = stops_name(cfg) else {
        return Ok(None);
    };
    if !cfg.track_follow {
        return Err(config_error(
            KEY,
            "stop points are braked for by the follow rule: set `backbone.track_follow = true`".into(),
        ));
    }
    let i = index(KEY, name)?;
    let Some(st) = &layout.segments()[i].stops else {
        return Err(config_error(
            KEY,
            format!("modality `{name}` does not declare slots of stop points"),
        ));
    };
    Ok(Some(StopSpec {
        segment: i,
        slot: st.slot,
        values: st.values,
        fields: st.fields.map(|(j, b)| (j, (b.lo, b.hi, b.bins))),
        state: st.state,
        stop: st.stop.clone(),
        go: st.go.clone(),
        gap_m: StopSpec::GAP_M,
    }))
}
