//! `umgen viz`: a clip as BEV + camera pictures.

use crate::cli::VizArgs;
use anyhow::Context;
use umgen::UmgenConfig;
use umgen::modality::{Mark, ModalityRegistry};
use umgen::scene::Frame;
use umgen_data::Dataset;
use umgen_render::{Camera, MapView};

/// Draws the requested frames of a clip, or a generated scene, into a GIF (and PNGs).
pub fn run(a: &VizArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    if let Some(dir) = &a.generated {
        return generated(a, dir, kinds);
    }
    let data = a.data.as_ref().context("--data or --generated")?;
    let ds = Dataset::open(data)?;
    let clip = if a.clip == "first" {
        anyhow::ensure!(!ds.clips().is_empty(), "{} has no clips", data.display());
        0
    } else {
        ds.find_clip(&a.clip)?
    };
    let entry = &ds.clips()[clip];
    let gap = a.gap.max(1);
    let available = entry.frames.saturating_sub(a.start).div_ceil(gap);
    let n = a.frames.unwrap_or(available).min(available);
    anyhow::ensure!(
        n > 0,
        "clip `{}` has {} frames; nothing to draw from frame {}",
        entry.id,
        entry.frames,
        a.start
    );
    let scene = ds.read_window(clip, a.start, n, gap)?;
    let registry = match &a.config {
        Some(path) => {
            let (config, missing) = UmgenConfig::load(path, &[])?.without_missing_tokenizers();
            for m in missing {
                tracing::warn!("modality `{m}`: its tokenizer does not exist; it draws no marks");
            }
            Some(config.registry(&kinds.catalog()?)?)
        }
        None => None,
    };
    let network = scene.network.clone().context("the clip has no road network")?;
    let view = MapView {
        size: [a.size, a.size],
        ..MapView::default()
    };
    let camera = Camera::default();
    if let Some(dir) = &a.png_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let bar = indicatif::ProgressBar::new(n as u64).with_message("drawing");
    let mut pictures = Vec::with_capacity(n);
    for (i, f) in scene.frames.iter().enumerate() {
        let pose = f.ego.pose2();
        let raster = view.render(&network, &pose);
        let image = camera.render(&network, &pose, &f.agents);
        let label = format!("{} T={:.1}S {} AGENTS", entry.id, f.time, f.agents.len());
        let marks = registry.as_ref().map(|r| marks(r, f)).unwrap_or_default();
        let pic = umgen_viz::scene_picture(&view, Some(&raster), Some(&image), f, &marks, &label);
        if let Some(dir) = &a.png_dir {
            umgen_viz::write_png(&dir.join(format!("frame-{i:04}.png")), &pic)?;
        }
        pictures.push(pic);
        bar.inc(1);
    }
    bar.finish_and_clear();
    umgen_viz::write_gif(&a.out, &pictures, scene.interval)?;
    tracing::info!("{}: {n} frames of clip `{}`", a.out.display(), entry.id);
    Ok(())
}

/// A scene of `umgen generate`'s output: its token rows decoded with the bundle it names.
fn generated(a: &VizArgs, dir: &std::path::Path, kinds: &crate::Kinds) -> anyhow::Result<()> {
    let super::scenes::Output {
        meta,
        tokens,
        bundle,
        registry,
    } = super::scenes::open_output(dir, a.bundle.as_deref(), kinds)?;
    let scenes = tokens["scenes"].as_array().context("tokens.json: no `scenes`")?;
    let scene = scenes.get(a.scene).with_context(|| {
        format!(
            "--scene {}: {} holds scenes 0..{}",
            a.scene,
            dir.display(),
            scenes.len()
        )
    })?;
    let rows: Vec<Vec<u32>> = serde_json::from_value(scene.clone()).context("tokens.json: scene rows")?;
    let context = tokens["context_frames"].as_u64().unwrap_or(0) as usize;
    let interval = meta["interval"].as_f64().unwrap_or(0.5);
    let (clip, malformed) = super::scenes::decode(&registry, &rows, &Frame::default(), interval)?;
    if malformed > 0 {
        tracing::warn!("{malformed} malformed token group(s) were skipped while decoding");
    }
    super::scenes::draw(&bundle, &registry, &clip, &a.out, a.png_dir.as_deref(), context)?;
    tracing::info!(
        "{}: scene {} ({context} context + {} generated frames)",
        a.out.display(),
        a.scene,
        rows.len() - context
    );
    Ok(())
}

/// What every modality of `registry` marks on the BEV of `frame`.
pub fn marks(registry: &ModalityRegistry, frame: &Frame) -> Vec<Mark> {
    registry
        .modalities()
        .iter()
        .flat_map(|m| m.marks(frame))
        .collect()
}
