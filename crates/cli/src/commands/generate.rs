//! `umgen generate`: roll a bundle's model forward from a dataset clip or from nothing, decode the frames
//! and draw them.

use crate::cli::GenerateArgs;
use crate::device::Device;
use anyhow::Context;
use burn::tensor::backend::AutodiffBackend;
use std::path::Path;
use umgen::backbone::Backbone;
use umgen::checkpoint::burn_io::weights_from_bytes;
use umgen::data::Dataset;
use umgen::generate::{Control, FrameControl, Generator, Sampling};
use umgen::scene::SceneClip;
use umgen::{Bundle, backbone_spec, builtin_catalog_with};

/// Generates.
pub fn run(a: &GenerateArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.scenes >= 1, "--scenes must be at least 1");
    let device = Device::parse(&a.device)?;
    let (bundle, registry) = Bundle::open_with(&a.bundle, &builtin_catalog_with(device.codec_loader())?)?;
    let spec = backbone_spec(&registry, &bundle.config.backbone)?;
    let control = match &a.control {
        Some(p) => read_control(p)?,
        None => Control::default(),
    };
    control.validate().with_context(|| {
        a.control
            .as_ref()
            .map_or(String::new(), |p| p.display().to_string())
    })?;
    let (context, interval) = context_clip(a)?;
    let context_rows = match &context {
        Some(c) => registry.tokenize_clip(&c.clip)?,
        None => Vec::new(),
    };
    let sampling = Sampling {
        top_k: a.top_k,
        top_p: a.top_p,
        temperature: a.temperature,
    };
    let bins = spec.action.as_ref().map(|x| x.bins);
    let agents = super::agents::AgentSlots::of(&bundle, &registry)?;
    let groups: Vec<_> = agents.iter().map(|a| a.groups()).collect();
    let started = std::time::Instant::now();
    let scenes = crate::with_autodiff!(device, |B, dev| {
        type I = <B as AutodiffBackend>::InnerBackend;
        let model = Backbone::<I>::new(&bundle.config.backbone, &spec, &dev)?;
        let model = weights_from_bytes(model, bundle.weights_f32()?, "bundle weights")?;
        let window = a.window.unwrap_or_else(|| {
            let w = 20.min(model.max_frames());
            if w < 20 {
                tracing::info!("conditioning on {w} frames (backbone.max_frames)");
            }
            w
        });
        let mut g = Generator::new(&model, vec![sampling; spec.segments.len()], window, a.seed)?;
        let mut history = vec![context_rows.clone(); a.scenes];
        let bar = crate::progress::bar(a.frames as u64, "frames")?;
        for k in 0..a.frames {
            let forced = bins.and_then(|b| control.action_at(k, &b));
            if let Some((_, clamped)) = &forced
                && *clamped > 0
            {
                tracing::warn!("frame {k}: {clamped} forced action value(s) outside the bins, clamped");
            }
            let ((placed, below), keep) = match &agents {
                Some(slots) => (slots.placement(&control, k)?, slots.keep(&history)),
                None => {
                    anyhow::ensure!(
                        control.agents_at(k).next().is_none(),
                        "the control file sets agents, but this model has no agent modality"
                    );
                    Default::default()
                }
            };
            let fc = FrameControl {
                action: forced.map(|(ids, _)| vec![ids; a.scenes]),
                tokens: placed,
                below,
                keep,
                groups: groups.clone(),
            };
            let next = g.next_frame(&history, &fc)?;
            for (h, f) in history.iter_mut().zip(next) {
                h.push(f);
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        history
    });
    let elapsed = started.elapsed().as_secs_f64();
    let tokens = (a.frames * a.scenes * spec.n) as f64;
    tracing::info!(
        "generated {} frame(s) × {} scene(s) in {elapsed:.1} s ({:.0} tokens/s, {:.2} frames/s)",
        a.frames,
        a.scenes,
        tokens / elapsed,
        (a.frames * a.scenes) as f64 / elapsed
    );
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let n_context = context_rows.len();
    std::fs::write(
        a.out.join("tokens.json"),
        serde_json::to_vec(&serde_json::json!({
            "n": spec.n, "context_frames": n_context, "fingerprint": bundle.manifest.fingerprint, "scenes": scenes,
        }))?,
    )?;
    let start = context
        .as_ref()
        .and_then(|c| c.clip.frames.last().cloned())
        .unwrap_or_default();
    let mut decoded = Vec::with_capacity(scenes.len());
    let mut malformed = 0;
    for rows in &scenes {
        let (clip, bad) = super::scenes::decode(&registry, &rows[n_context..], &start, interval)?;
        malformed += bad;
        decoded.push(clip);
    }
    if malformed > 0 {
        tracing::warn!("{malformed} malformed token group(s) were skipped while decoding");
    }
    let light: Vec<SceneClip> = decoded
        .iter()
        .map(|c| {
            let mut c = c.clone();
            c.frames.iter_mut().for_each(|f| (f.map, f.image) = (None, None));
            c
        })
        .collect();
    std::fs::write(a.out.join("scenes.json"), serde_json::to_vec(&light)?)?;
    let network = context.as_ref().and_then(|c| c.clip.network.clone());
    write_dataset(&a.out.join("dataset"), light, network)?;
    // What `umgen eval` needs to find the ground truth and the tokenizers.
    let context_meta = context
        .as_ref()
        .map(|c| serde_json::json!({"data": c.data, "clip": c.id, "frames": n_context}));
    std::fs::write(
        a.out.join("meta.json"),
        serde_json::to_vec_pretty(&serde_json::json!({
            "bundle": std::fs::canonicalize(&a.bundle).unwrap_or_else(|_| a.bundle.clone()),
            "context": context_meta,
            "frames": a.frames,
            "scenes": a.scenes,
            "seed": a.seed,
            "interval": interval,
        }))?,
    )?;
    super::scenes::draw(
        &bundle,
        &decoded[0],
        &a.out.join("rollout.gif"),
        a.png.then_some(a.out.as_path()),
        0,
    )?;
    tracing::info!(
        "{}: tokens.json, scenes.json, dataset/, rollout.gif ({} context + {} generated frames)",
        a.out.display(),
        n_context,
        a.frames
    );
    Ok(())
}

/// The decoded scenes as a umgen dataset in `dir` (replacing one from an earlier run), on the context clip's
/// road network: ego and agent tracks in world coordinates, one clip per scene, split `generated`. Generated
/// map and image tokens are not part of it (a dataset derives those from its network).
fn write_dataset(
    dir: &Path,
    mut scenes: Vec<SceneClip>,
    network: Option<std::sync::Arc<umgen::scene::RoadNetwork>>,
) -> anyhow::Result<()> {
    for c in &mut scenes {
        c.network = network.clone();
    }
    let partial = dir.with_extension("partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial).with_context(|| format!("removing {}", partial.display()))?;
    }
    umgen::data::write_scene_dataset(&partial, &scenes, "scene", "generated")?;
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("replacing {}", dir.display()))?;
    }
    std::fs::rename(&partial, dir).with_context(|| format!("writing {}", dir.display()))?;
    Ok(())
}

fn read_control(p: &Path) -> anyhow::Result<Control> {
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    let c = if p.extension().is_some_and(|e| e == "json") {
        serde_json::from_str(&text).with_context(|| p.display().to_string())?
    } else {
        toml::from_str(&text).with_context(|| p.display().to_string())?
    };
    Ok(c)
}

/// The context (`--context DATA:CLIP[:FRAMES]`): its frames, and the dataset and clip id for `meta.json`.
struct ContextClip {
    clip: SceneClip,
    data: String,
    id: String,
}

/// The context clip, if any, and the frame interval.
fn context_clip(a: &GenerateArgs) -> anyhow::Result<(Option<ContextClip>, f64)> {
    let Some(spec) = &a.context else {
        anyhow::ensure!(
            a.from_scratch,
            "give --context DATA:CLIP[:FRAMES] or --from-scratch"
        );
        return Ok((None, 0.5));
    };
    // Clip ids may hold ':' themselves (`rand-s3/v0:2`): a numeric suffix is a frame count only when
    // the whole rest is not a clip id.
    let (data, rest) = spec
        .split_once(':')
        .with_context(|| format!("--context {spec}: expected DATA:CLIP or DATA:CLIP:FRAMES"))?;
    let ds = Dataset::open(Path::new(data))?;
    let (index, frames) = match ds.find_clip(rest) {
        Ok(i) => (i, None),
        Err(e) => match rest.rsplit_once(':') {
            Some((clip, f)) if f.parse::<usize>().is_ok() => (ds.find_clip(clip)?, f.parse::<usize>().ok()),
            _ => return Err(e.into()),
        },
    };
    let available = ds.clips()[index].frames;
    let n = frames.unwrap_or(a.window.unwrap_or(20)).min(available);
    anyhow::ensure!(n > 0, "--context {spec}: the clip has no frames");
    let clip = ds.read_window(index, 0, n, 1)?;
    let interval = clip.interval;
    let id = ds.clips()[index].id.clone();
    Ok((
        Some(ContextClip {
            clip,
            data: data.to_string(),
            id,
        }),
        interval,
    ))
}
