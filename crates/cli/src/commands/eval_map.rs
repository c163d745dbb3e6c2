//! The map part of `umgen eval`: per second generated, each layer's IoU (and F1 within one pixel) of the
//! map decoded from the generated map codes with the map rendered from the context clip's road network at
//! the generated ego pose, cells pooled over the frames as the tokenizer's own evaluation pools them
//! ([`IouCounter`]). The context frames give the reference: their real codes decoded against the map at
//! their real poses, what the map tokenizer alone keeps. Beside it, how the frame's vehicles sit on the
//! map its own codes draw (all of them, those entering the frame, and of those off it the share that
//! entered off it): a scene that places vehicles off its own roads is inconsistent whatever the real road
//! does, and whether they drove off or came in off tells where to look.

use std::collections::HashMap;

use anyhow::Context;
use umgen::data::Dataset;
use umgen::modality::{Modality, ModalityRegistry, Segment};
use umgen::scene::{Agent, AgentCategory, Frame, MapRaster, RoadNetwork, SceneClip};
use umgen::tokenizer_vq::IouCounter;
use umgen_eval::horizon::second_of;
use umgen_render::MapView;

use super::eval_seen::{ContextView, Seen};

/// Frames pooled: the counts and how many frames went in.
#[derive(Default)]
struct Pooled {
    iou: IouCounter,
    frames: usize,
    /// Vehicles inside the raster, and those whose centre's cell no drivable layer covers.
    vehicles: usize,
    vehicles_off: usize,
    /// The same for vehicles absent from the frame before.
    entering: usize,
    entering_off: usize,
    /// Vehicles off the map that entered off it (in their sequence's frames seen so far).
    off_entered_off: usize,
    /// The same frames within the context's view.
    seen: Seen,
}

/// Per vehicle (`track_id`) of one sequence of frames, whether it was off the map in the frame it entered.
type Entered = HashMap<u64, bool>;

impl Pooled {
    /// `{"frames", "iou": [per layer], "f1_within_1px": [per layer], "vehicles_off_map",
    /// "entering_off_map", "off_map_entered_off", "context_view"}` ([`Seen::json`]).
    fn json(&self) -> serde_json::Value {
        let f1: Vec<Option<f64>> = self.iou.near().iter().map(|n| n.map(|n| n.f1)).collect();
        let share = |n: usize, of: usize| (of > 0).then(|| n as f64 / of as f64);
        serde_json::json!({
            "frames": self.frames,
            "iou": self.iou.iou(),
            "f1_within_1px": f1,
            "vehicles_off_map": share(self.vehicles_off, self.vehicles),
            "entering_off_map": share(self.entering_off, self.entering),
            "off_map_entered_off": share(self.off_entered_off, self.vehicles_off),
            "context_view": self.seen.json(),
        })
    }

    /// Counts the vehicles of `agents` against the drivable `channels` of `map` (decoded with `view`);
    /// those not in `before` (when known) also as entering, and records in `entered` where they entered.
    /// Vehicles outside the raster are left out.
    fn add_vehicles(
        &mut self,
        view: &MapView,
        map: &MapRaster,
        channels: &[usize],
        agents: &[Agent],
        before: Option<&[Agent]>,
        entered: &mut Entered,
    ) {
        for a in agents.iter().filter(|a| a.category == AgentCategory::Vehicle) {
            let Some(on) = view.covers(map, channels, [a.x, a.y]) else {
                continue;
            };
            let off = usize::from(!on);
            self.vehicles += 1;
            self.vehicles_off += off;
            if before.is_some_and(|b| !b.iter().any(|o| o.track_id == a.track_id)) {
                self.entering += 1;
                self.entering_off += off;
                entered.insert(a.track_id, !on);
            }
            self.off_entered_off += usize::from(!on && entered.get(&a.track_id) == Some(&true));
        }
    }
}

/// The cells of a raster as the map modality reads them: set above 127.
fn cells(r: &MapRaster) -> Vec<f32> {
    r.data.iter().map(|&v| if v > 127 { 1.0 } else { 0.0 }).collect()
}

/// The map modality and its segment of the frame layout: what decodes a row's map codes.
type MapCodes<'a> = (&'a dyn Modality, &'a Segment);

/// Decodes the map codes of `row` (the other modalities are not decoded) and adds the map, against
/// `network` rendered at the pose of `frame` (also within `context`'s view), to `pooled`, with the vehicles of `frame` on it (entering
/// ones against `before`, the frame before it, recorded in `entered`); false when the codes decode to no
/// map raster.
#[allow(clippy::too_many_arguments)]
fn add_frame(
    (map, seg): MapCodes<'_>,
    view: &MapView,
    row: &[u32],
    (network, context): (&RoadNetwork, &ContextView),
    frame: &Frame,
    before: Option<&Frame>,
    pooled: &mut Pooled,
    entered: &mut Entered,
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
    let rendered = view.render(network, &frame.ego.pose2());
    let shape = |r: &MapRaster| [r.channels, r.height, r.width];
    anyhow::ensure!(
        shape(&decoded) == shape(&rendered),
        "the map codes decode to a {:?} raster but the map modality renders {:?} (channels, rows, columns)",
        shape(&decoded),
        shape(&rendered)
    );
    let [c, h, w] = shape(&rendered);
    let (decoded_cells, rendered_cells) = (cells(&decoded), cells(&rendered));
    pooled.iou.add(c, [h, w], &decoded_cells, &rendered_cells);
    pooled.frames += 1;
    let channels = view.drivable_channels();
    let pose = frame.ego.pose2();
    pooled.seen.add(
        context,
        view,
        &pose,
        &decoded_cells,
        &rendered_cells,
        &rendered,
        &channels,
        frame,
        before,
    );
    let before = before.map(|b| &b.agents[..]);
    pooled.add_vehicles(view, &decoded, &channels, &frame.agents, before, entered);
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
        let shown = ContextView::new(&real.frames, view);
        let first = c * per;
        let add = |row: &[u32], f: &Frame, before, pooled: &mut Pooled, entered: &mut Entered| {
            add_frame(map, view, row, (&network, &shown), f, before, pooled, entered)
                .map(|ok| usize::from(!ok))
        };
        // The context rows are the real frames' codes, the same in each of the context's scenes.
        let mut entered = Entered::new();
        for (k, (row, f)) in rows[first][..n_context].iter().zip(&real.frames).enumerate() {
            let before = k.checked_sub(1).map(|j| &real.frames[j]);
            without += add(row, f, before, &mut context, &mut entered)?;
        }
        for s in first..first + per {
            let mut entered = Entered::new();
            for (k, (row, f)) in rows[s][n_context..].iter().zip(&scenes[s].frames).enumerate() {
                let second = second_of(k + 1, dt);
                if seconds.len() < second {
                    seconds.resize_with(second, Pooled::default);
                }
                let before = k.checked_sub(1).map(|j| &scenes[s].frames[j]);
                without += add(row, f, before, &mut seconds[second - 1], &mut entered)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use umgen::scene::{MapLayer, Pose2};
    use umgen_eval::collision::bev_box;

    fn agent(id: u64, category: AgentCategory, x: f64, y: f64) -> Agent {
        Agent {
            track_id: id,
            category,
            ..bev_box(x, y, 0.0, 4.0, 2.0)
        }
    }

    /// The map renderer draws a road along global x, 4 m wide; vehicles are tested against the raster
    /// it draws at the ego pose, so the pixel lookup must agree with the renderer's own placement.
    #[test]
    fn vehicles_on_the_map_their_codes_draw() {
        let network = RoadNetwork {
            lanes: vec![vec![[-200.0, -2.0], [200.0, -2.0], [200.0, 2.0], [-200.0, 2.0]]],
            ..RoadNetwork::default()
        };
        let view = MapView {
            extent_m: 128.0,
            size: [64, 64],
            layers: MapLayer::ALL.to_vec(),
        };
        let channels = view.drivable_channels();
        assert_eq!(channels.len(), 3, "lane, intersection, lane connector");
        let (car, walker) = (AgentCategory::Vehicle, AgentCategory::Pedestrian);
        // The ego on the road facing along it.
        let map = view.render(&network, &Pose2::new(0.0, 0.0, 0.0));
        let before = [agent(1, car, 10.0, 0.0), agent(2, walker, 10.0, 20.0)];
        let now = [
            agent(1, car, 12.0, 0.0),    // stays, on the road
            agent(3, car, -30.0, 10.0),  // enters beside the road
            agent(4, car, 40.0, 0.5),    // enters on it
            agent(5, car, 70.0, 0.0),    // outside the raster: not counted
            agent(6, walker, 0.0, -9.0), // a pedestrian: not counted
        ];
        let mut p = Pooled::default();
        let mut entered = Entered::new();
        p.add_vehicles(&view, &map, &channels, &now, Some(&before), &mut entered);
        assert_eq!((p.vehicles, p.vehicles_off), (3, 1));
        assert_eq!((p.entering, p.entering_off), (2, 1));
        assert_eq!(p.off_entered_off, 1, "3 entered off the road and is off it");
        // A frame later 3 is still off, 1 left the road, 4 is on it: of the 3 off now (3 of the first
        // frame, 3 and 1 of this one), 2 entered off it.
        let later = [agent(1, car, 14.0, 9.0), now[1], now[2]];
        p.add_vehicles(&view, &map, &channels, &later, Some(&now), &mut entered);
        assert_eq!((p.vehicles_off, p.off_entered_off), (3, 2));
        assert_eq!(p.json()["off_map_entered_off"].as_f64(), Some(2.0 / 3.0));
        // Without the frame before, nothing counts as entering.
        let mut first = Pooled::default();
        first.add_vehicles(&view, &map, &channels, &now, None, &mut Entered::new());
        assert_eq!((first.vehicles, first.entering, first.off_entered_off), (3, 0, 0));
        let j = first.json();
        assert_eq!(j["vehicles_off_map"].as_f64(), Some(1.0 / 3.0));
        assert!(j["entering_off_map"].is_null(), "{j}");
        // The ego turned left across the road: its x is global y, its y global −x. (0, −20) lies on the
        // road 20 m along global x; (20, 0) lies 20 m off it.
        let turned = view.render(&network, &Pose2::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
        let on = |p: [f64; 2]| view.covers(&turned, &channels, p);
        assert_eq!((on([0.0, -20.0]), on([20.0, 0.0])), (Some(true), Some(false)));
        assert_eq!(on([0.0, 64.5]), None, "beyond the raster's edge");
    }
}
