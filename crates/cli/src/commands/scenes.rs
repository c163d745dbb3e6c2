//! Generated scenes: decoding token rows into frames and drawing them (`umgen generate`, `umgen viz
//! --generated`).

use anyhow::Context;
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use umgen::Bundle;
use umgen::data::Dataset;
use umgen::modality::ModalityRegistry;
use umgen::scene::{Frame, RoadNetwork, SceneClip};

/// A JSON file of a `umgen generate` output directory.
pub fn read_json(dir: &Path, name: &str) -> anyhow::Result<serde_json::Value> {
    let p = dir.join(name);
    let bytes = std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
    serde_json::from_slice(&bytes).with_context(|| p.display().to_string())
}

/// A `umgen generate` output directory, opened by [`open_output`].
pub struct Output {
    /// Its `meta.json`.
    pub meta: serde_json::Value,
    /// Its `tokens.json`.
    pub tokens: serde_json::Value,
    /// The bundle that decodes the tokens.
    pub bundle: Bundle,
    /// That bundle's modalities.
    pub registry: ModalityRegistry,
}

/// A `umgen generate` output directory: its `meta.json` and `tokens.json`, the bundle `meta.json` names
/// (or `bundle`, which must have the layout the tokens were drawn in) and that bundle's modalities.
pub fn open_output(dir: &Path, bundle: Option<&Path>, kinds: &crate::Kinds) -> anyhow::Result<Output> {
    let meta = read_json(dir, "meta.json")?;
    let named = meta["bundle"].as_str().context("meta.json: no `bundle`")?;
    let bundle_dir = bundle.unwrap_or(Path::new(named));
    let (bundle, registry) = Bundle::open_with(bundle_dir, &kinds.catalog()?)
        .with_context(|| format!("the bundle of {} (--bundle names another)", dir.display()))?;
    // Tokens are only read right with the layout they were drawn in.
    let tokens = read_json(dir, "tokens.json")?;
    let drawn = tokens["fingerprint"].as_str().unwrap_or("(none recorded)");
    anyhow::ensure!(
        drawn == bundle.manifest.fingerprint,
        "{}: its tokens were drawn with the layout {drawn}, the bundle {} has the layout {}",
        dir.display(),
        bundle_dir.display(),
        bundle.manifest.fingerprint
    );
    Ok(Output {
        meta,
        tokens,
        bundle,
        registry,
    })
}

/// Decodes generated rows into frames, integrating the ego pose from `start` by each decoded action.
pub fn decode(
    registry: &ModalityRegistry,
    rows: &[Vec<u32>],
    start: &Frame,
    interval: f64,
) -> anyhow::Result<(SceneClip, u64)> {
    decode_except(registry, rows, start, interval, &[])
}

/// [`decode`] without the modalities of the kinds `skip` (their parts of each frame stay empty).
pub fn decode_except(
    registry: &ModalityRegistry,
    rows: &[Vec<u32>],
    start: &Frame,
    interval: f64,
    skip: &[&str],
) -> anyhow::Result<(SceneClip, u64)> {
    let mut frames = Vec::with_capacity(rows.len());
    let mut prev = start.clone();
    let mut malformed = 0;
    for row in rows {
        let mut f = Frame::default();
        malformed += registry.detokenize_except(row, &mut f, skip)?.malformed;
        f.time = prev.time + interval;
        f.ego = prev.ego.advance(&f.action, interval);
        prev = f.clone();
        frames.push(f);
    }
    Ok((SceneClip::new("generated", interval, frames)?, malformed))
}

/// The kinds of the raster modalities, whose VQ decoders take most of the decoding time of a large
/// batch, and whose rasters `scenes.json` does not hold.
pub const RASTERS: &[&str] = &[umgen::modality_map::KIND, umgen::modality_image::KIND];

/// Where a scene's decoding starts: the last frame of its context clip and that clip's road network.
pub type Start = (Frame, Option<Arc<RoadNetwork>>);

/// Decodes each scene's generated rows, `scenes[s][n_context..]`, scene `s` from
/// `starts[context_of[s]]` (from nothing without a context) and on its network, without the
/// modalities of the kinds `skip(s)`; logs the malformed token groups skipped.
pub fn decode_rollout<'k>(
    registry: &ModalityRegistry,
    scenes: &[Vec<Vec<u32>>],
    n_context: usize,
    interval: f64,
    (context_of, starts): (&[Option<usize>], &[Start]),
    skip: impl Fn(usize) -> &'k [&'k str],
) -> anyhow::Result<Vec<SceneClip>> {
    let mut malformed = 0;
    let mut decoded = Vec::with_capacity(scenes.len());
    for (s, rows) in scenes.iter().enumerate() {
        let context = context_of.get(s).copied().flatten().and_then(|c| starts.get(c));
        let start = context.map(|c| c.0.clone()).unwrap_or_default();
        let generated = rows.get(n_context..).unwrap_or_default();
        let (mut clip, bad) = decode_except(registry, generated, &start, interval, skip(s))?;
        clip.network = context.and_then(|c| c.1.clone());
        malformed += bad;
        decoded.push(clip);
    }
    if malformed > 0 {
        tracing::warn!("{malformed} malformed token group(s) were skipped while decoding");
    }
    Ok(decoded)
}

/// The decoded scenes of a `umgen generate` output directory `dir`: its `scenes.json`, or, where only
/// its `tokens.json` and `meta.json` were kept, the tokens decoded as `generate` decodes them (each
/// scene from the last frame of its context clip, read again from the dataset `meta.json` names, and
/// on that clip's road network).
pub fn generated_scenes(dir: &Path, out: &Output) -> anyhow::Result<Vec<SceneClip>> {
    let written = dir.join("scenes.json");
    if written.exists() {
        return serde_json::from_value(read_json(dir, "scenes.json")?).context("scenes.json");
    }
    let rows: Vec<Vec<Vec<u32>>> =
        serde_json::from_value(out.tokens["scenes"].clone()).context("tokens.json: scenes")?;
    let n_context = out.tokens["context_frames"].as_u64().unwrap_or(0) as usize;
    let context_of: Vec<Option<usize>> =
        serde_json::from_value(out.tokens["context_of"].clone()).context("tokens.json: context_of")?;
    let interval = out.meta["interval"].as_f64().context("meta.json: interval")?;
    let contexts = out.meta["contexts"].as_array().context("meta.json: contexts")?;
    // The contexts of a batch mostly come from one dataset: each is opened once.
    let mut datasets: HashMap<&str, Dataset> = HashMap::new();
    let mut starts = Vec::with_capacity(contexts.len());
    for c in contexts {
        let data = c["data"].as_str().context("meta.json: contexts[].data")?;
        let id = c["clip"].as_str().context("meta.json: contexts[].clip")?;
        let ds = match datasets.entry(data) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => e.insert(Dataset::open(Path::new(data))?),
        };
        let clip = ds.read_window(ds.find_clip(id)?, 0, n_context.max(1), 1)?;
        starts.push((clip.frames.last().cloned().unwrap_or_default(), clip.network));
    }
    tracing::info!(
        "{}: no scenes.json; decoding the {} scenes of tokens.json",
        dir.display(),
        rows.len()
    );
    decode_rollout(
        &out.registry,
        &rows,
        n_context,
        interval,
        (&context_of, &starts),
        |_| RASTERS,
    )
}

/// The map renderer of the bundle's map modality (raster size, extent, layers), if it has one.
pub fn map_view(bundle: &Bundle) -> anyhow::Result<Option<umgen_render::MapView>> {
    Ok(bundle
        .config
        .modality
        .iter()
        .find_map(|(name, table)| {
            let kind = table.get("kind").and_then(|k| k.as_str()).unwrap_or(name);
            (kind == umgen::modality_map::KIND)
                .then(|| umgen::modality::parse_settings::<umgen::modality_map::MapConfig>(name, table))
                .map(|c| c.and_then(|c| c.map_view(name)))
        })
        .transpose()?)
}

/// A decoded scene as a GIF (and `frame-NNNN.png` into `png_dir`): BEV from the decoded map raster with the
/// decoded agents, camera below; the first `context` frames are labelled CTX, the others GEN.
pub fn draw(
    bundle: &Bundle,
    registry: &ModalityRegistry,
    clip: &SceneClip,
    gif: &Path,
    png_dir: Option<&Path>,
    context: usize,
) -> anyhow::Result<()> {
    let view = map_view(bundle)?.unwrap_or_default();
    let pictures: Vec<_> = clip
        .frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            // Small rasters (the tiny config's 64 px) are enlarged to about 256 px wide.
            let k = (256 / view.size[1].max(1)).max(1);
            let marks = super::viz::marks(registry, f);
            let mut pic =
                umgen_viz::scene_picture(&view, f.map.as_ref(), f.image.as_ref(), f, &marks, "").scaled(k);
            let label = if i < context {
                format!("CTX {i} {} AGENTS", f.agents.len())
            } else {
                format!("GEN {} {} AGENTS", i - context, f.agents.len())
            };
            umgen_viz::text(&mut pic, 4, 4, 2, &label, [250, 250, 250]);
            pic
        })
        .collect();
    if let Some(dir) = png_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for (i, p) in pictures.iter().enumerate() {
            umgen_viz::write_png(&dir.join(format!("frame-{i:04}.png")), p)?;
        }
    }
    umgen_viz::write_gif(gif, &pictures, clip.interval)?;
    Ok(())
}
