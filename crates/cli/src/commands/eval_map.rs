//! The map part of `umgen eval`: per second generated, each layer's IoU (and F1 within one pixel) of the
//! map decoded from the generated map codes with the map rendered from the context clip's road network at
//! the generated ego pose, cells pooled over the frames as the tokenizer's own evaluation pools them
//! ([`IouCounter`]). The context frames give the reference: their real codes decoded against the map at
//! their real poses, what the map tokenizer alone keeps.

use anyhow::Context;
use umgen::data::Dataset;
use umgen::modality::{Modality, ModalityRegistry, Segment};
use umgen::scene::{Frame, MapRaster, Pose2, RoadNetwork, SceneClip};
use umgen::tokenizer_vq::IouCounter;
use umgen_eval::horizon::second_of;
use umgen_render::MapView;

/// Frames pooled: the counts and how many frames went in.
#[derive(Default)]
struct Pooled {
    iou: IouCounter,
    frames: usize,
}

impl Pooled {
    /// `{"frames", "iou": [per layer], "f1_within_1px": [per layer]}`.
    fn json(&self) -> serde_json::Value {
        let f1: Vec<Option<f64>> = self.iou.near().iter().map(|n| n.map(|n| n.f1)).collect();
        serde_json::json!({"frames": self.frames, "iou": self.iou.iou(), "f1_within_1px": f1})
    }
}

/// The cells of a raster as the map modality reads them: set above 127.
fn cells(r: &MapRaster) -> Vec<f32> {
    r.data.iter().map(|&v| if v > 127 { 1.0 } else { 0.0 }).collect()
}

/// The map modality and its segment of the frame layout: what decodes a row's map codes.
type MapCodes<'a> = (&'a dyn Modality, &'a Segment);

/// Decodes the map codes of `row` (the other modalities are not decoded) and adds the map, against
/// `network` rendered at `pose`, to `pooled`; false when the codes decode to no map raster.
fn add_frame(
    (map, seg): MapCodes<'_>,
    view: &MapView,
    row: &[u32],
    network: &RoadNetwork,
    pose: &Pose2,
    pooled: &mut Pooled,
) -> anyhow::Result<bool> {
    let codes = row.get(seg.content()).with_context(|| {
        format!(
            "tokens.json: a row of {} tokens has no `{}` codes at {:?}",
            row.len(),
            seg.modality,
            seg.content()
        )
    })?;
    let mut f = Frame::default();
    map.detokenize(codes, &mut f)?;
    let Some(decoded) = f.map else {
        return Ok(false);
    };
    let rendered = view.render(network, pose);
    let shape = |r: &MapRaster| [r.channels, r.height, r.width];
    anyhow::ensure!(
        shape(&decoded) == shape(&rendered),
        "the map codes decode to a {:?} raster but the map modality renders {:?} (channels, rows, columns)",
        shape(&decoded),
        shape(&rendered)
    );
    let [c, h, w] = shape(&rendered);
    pooled.iou.add(c, [h, w], &cells(&decoded), &cells(&rendered));
    pooled.frames += 1;
    Ok(true)
}

/// `{"layers", "context", "seconds": [{"second", "frames", "iou"}]}` for generated `scenes` whose scene `s`
/// continues `contexts[s / per]` of `ds`, their token rows `tokens` (tokens.json) decoded with `registry`
/// and the bundle's map `view`; `None` without a map modality or without contexts (scenes from scratch have
/// no real map).
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
    let Some(map) = super::agents::modality_of_kind(registry, umgen::modality_map::KIND)? else {
        return Ok(None);
    };
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
    let (mut context, mut seconds, mut without) = (Pooled::default(), Vec::<Pooled>::new(), 0usize);
    for (c, ctx) in contexts.iter().enumerate() {
        let id = ctx["clip"].as_str().context("meta.json: contexts[].clip")?;
        let idx = ds.find_clip(id)?;
        // The clip's frames come with its road network (the dataset reads each network once).
        let real = ds.read_window(idx, 0, n_context, 1)?;
        let Some(network) = real.network.clone() else {
            continue;
        };
        let first = c * per;
        // The context rows are the real frames' codes, the same in each of the context's scenes.
        for (row, f) in rows[first][..n_context].iter().zip(&real.frames) {
            without += usize::from(!add_frame(
                map,
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
                    seconds.resize_with(second, Pooled::default);
                }
                let pose = f.ego.pose2();
                without += usize::from(!add_frame(
                    map,
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
            let mut v = s.json();
            v["second"] = (i + 1).into();
            v
        })
        .collect();
    Ok(Some(serde_json::json!({
        "layers": view.layers.iter().map(|l| l.name()).collect::<Vec<_>>(),
        "context": context.json(),
        "seconds": rows,
    })))
}
