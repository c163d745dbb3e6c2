//! The map part of `umgen eval`: per second generated, each layer's IoU of the map decoded from the
//! generated map codes with the map rendered from the context clip's road network at the generated ego
//! pose ([`umgen_eval::map_iou`]). The context frames give the reference: their real codes decoded
//! against the map at their real poses, what the map tokenizer alone keeps.

use anyhow::Context;
use std::collections::HashMap;
use std::sync::Arc;
use umgen::data::Dataset;
use umgen::modality::ModalityRegistry;
use umgen::scene::{Frame, Pose2, RoadNetwork, SceneClip};
use umgen_eval::horizon::second_of;
use umgen_eval::map_iou::LayerIou;
use umgen_render::MapView;

/// Decodes `row` and adds its map, against `network` rendered at `pose`, to `iou`; false when the row
/// decodes to no map raster.
fn add_frame(
    registry: &ModalityRegistry,
    view: &MapView,
    row: &[u32],
    network: &RoadNetwork,
    pose: &Pose2,
    iou: &mut LayerIou,
) -> anyhow::Result<bool> {
    let mut f = Frame::default();
    registry.detokenize(row, &mut f)?;
    let Some(decoded) = f.map else {
        return Ok(false);
    };
    iou.add(&decoded, &view.render(network, pose))?;
    Ok(true)
}

/// The JSON of one pooled set of frames.
fn json(iou: &LayerIou) -> serde_json::Value {
    serde_json::json!({"frames": iou.frames(), "iou": iou.ious()})
}

/// `{"layers", "context", "seconds": [{"second", "frames", "iou"}]}` for generated `scenes` whose scene `s`
/// continues `contexts[s / per]` of `ds`, their token rows `tokens` (tokens.json) decoded with `registry`
/// and the bundle's map `view`; `None` without contexts (scenes from scratch have no real map).
#[allow(clippy::too_many_arguments)]
pub(super) fn map_consistency(
    view: &MapView,
    registry: &ModalityRegistry,
    tokens: &serde_json::Value,
    scenes: &[SceneClip],
    contexts: &[serde_json::Value],
    per: usize,
    ds: &Dataset,
    dt: f64,
) -> anyhow::Result<Option<serde_json::Value>> {
    if contexts.is_empty() {
        return Ok(None);
    }
    let rows: Vec<Vec<Vec<u32>>> =
        serde_json::from_value(tokens["scenes"].clone()).context("tokens.json: scenes")?;
    let n_context = tokens["context_frames"]
        .as_u64()
        .context("tokens.json: context_frames")? as usize;
    anyhow::ensure!(
        rows.len() == scenes.len(),
        "tokens.json holds {} scenes, scenes.json {}",
        rows.len(),
        scenes.len()
    );
    let mut networks: HashMap<String, Arc<RoadNetwork>> = HashMap::new();
    let (mut context, mut seconds, mut without) = (LayerIou::default(), Vec::<LayerIou>::new(), 0usize);
    for (c, ctx) in contexts.iter().enumerate() {
        let id = ctx["clip"].as_str().context("meta.json: contexts[].clip")?;
        let idx = ds.find_clip(id)?;
        let log = &ds.clips()[idx].log;
        let Some(net_id) = ds
            .index()
            .logs
            .iter()
            .find(|l| &l.id == log)
            .map(|l| l.network.clone())
        else {
            continue;
        };
        let network = match networks.get(&net_id) {
            Some(n) => n.clone(),
            None => {
                let n = ds.network(&net_id)?;
                networks.insert(net_id, n.clone());
                n
            }
        };
        let real = ds.read_window(idx, 0, n_context, 1)?;
        let first = c * per;
        // The context rows are the real frames' codes, the same in each of the context's scenes.
        for (row, f) in rows[first][..n_context].iter().zip(&real.frames) {
            without += usize::from(!add_frame(
                registry,
                view,
                row,
                &network,
                &f.ego.pose2(),
                &mut context,
            )?);
        }
        for s in first..first + per {
            for (k, (row, f)) in rows[s][n_context..].iter().zip(&scenes[s].frames).enumerate() {
                let second = second_of(k + 1, dt);
                if seconds.len() < second {
                    seconds.resize_with(second, LayerIou::default);
                }
                let pose = f.ego.pose2();
                without += usize::from(!add_frame(
                    registry,
                    view,
                    row,
                    &network,
                    &pose,
                    &mut seconds[second - 1],
                )?);
            }
        }
    }
    if without > 0 {
        tracing::warn!("{without} frame(s) decoded to no map raster and were left out of the map IoU");
    }
    let rows: Vec<serde_json::Value> = seconds
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut v = json(s);
            v["second"] = (i + 1).into();
            v
        })
        .collect();
    Ok(Some(serde_json::json!({
        "layers": view.layers.iter().map(|l| l.name()).collect::<Vec<_>>(),
        "context": json(&context),
        "seconds": rows,
    })))
}
