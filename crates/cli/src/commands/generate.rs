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
use umgen::modality::ModalityRegistry;
use umgen::scene::SceneClip;
use umgen::{Bundle, backbone_spec, builtin_catalog_with};

/// Generates.
pub fn run(a: &GenerateArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.scenes >= 1, "--scenes must be at least 1");
    let bundle = Bundle::open(&a.bundle)?;
    let device = Device::parse(&a.device)?;
    let registry = bundle
        .config
        .registry(&builtin_catalog_with(device.codec_loader())?)?;
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
    let groups = agent_groups(&bundle, &registry)?;
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
            let (placed, below) = agent_tokens(&bundle, &registry, &control, k)?;
            let keep = keep_agents(&registry, &history)?;
            let groups = groups.clone();
            let fc = FrameControl {
                action: forced.map(|(ids, _)| vec![ids; a.scenes]),
                tokens: placed.clone(),
                below,
                keep,
                groups,
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
        "{}: tokens.json, scenes.json, rollout.gif ({} context + {} generated frames)",
        a.out.display(),
        n_context,
        a.frames
    );
    Ok(())
}

/// Placed tokens and id limits for generated frame `k`: each value the control file sets, encoded with the
/// agent modality's bins (its `[modality.<name>]` table), and the slot's category are placed; the slot's
/// other attributes are drawn from the value bins only (never pad or a category).
type Placement = (Vec<(usize, u32)>, Vec<(usize, u32)>);

fn agent_tokens(
    bundle: &Bundle,
    registry: &ModalityRegistry,
    control: &Control,
    k: usize,
) -> anyhow::Result<Placement> {
    use umgen::modality_agent::{ATTRIBUTES, AgentConfig, VALUE_FIELDS};
    let (mut out, mut below) = (Vec::new(), Vec::new());
    let active: Vec<_> = control.agents_at(k).collect();
    if active.is_empty() {
        return Ok((out, below));
    }
    let layout = registry.layout()?;
    let seg = layout
        .segments()
        .iter()
        .find(|s| s.kind == umgen::modality_agent::KIND)
        .context("the control file sets agents, but this model has no agent modality")?;
    let table = bundle
        .config
        .modality
        .get(&seg.modality)
        .cloned()
        .unwrap_or_default();
    let cfg: AgentConfig = umgen::modality::parse_settings(&seg.modality, &table)?;
    let slots = seg.tokens / ATTRIBUTES;
    for (i, a) in active.iter().enumerate() {
        anyhow::ensure!(
            a.slot < slots,
            "agent[{i}].slot = {}: this model has slots 0..{slots}",
            a.slot
        );
        let base = seg.offset + a.slot * ATTRIBUTES;
        for (name, v) in a.values() {
            let f = VALUE_FIELDS
                .iter()
                .position(|x| *x == name)
                .context("unknown agent field")?;
            let [lo, hi] = cfg.ranges()[f];
            let bins = umgen::modality::ScalarBins::new(
                &format!("modality.{}.{name}", seg.modality),
                lo,
                hi,
                cfg.bins,
            )?;
            let (id, clamp) = bins.encode(v);
            if clamp.is_some() {
                tracing::warn!(
                    "frame {k}: agent slot {} {name} = {v} is outside [{lo}, {hi}], clamped",
                    a.slot
                );
            }
            out.push((base + f, id));
        }
        let category = match a.category.as_deref().unwrap_or("vehicle") {
            "pedestrian" => umgen::scene::AgentCategory::Pedestrian,
            "cyclist" => umgen::scene::AgentCategory::Cyclist,
            _ => umgen::scene::AgentCategory::Vehicle,
        };
        out.push((base + ATTRIBUTES - 1, cfg.category_id(category)));
        below.extend((0..ATTRIBUTES - 1).map(|f| (base + f, cfg.bins)));
    }
    Ok((out, below))
}

/// The agent slots as token groups: each comes out either empty (all pad) or as values and a category,
/// never a mix that decodes to nothing.
fn agent_groups(
    bundle: &Bundle,
    registry: &ModalityRegistry,
) -> anyhow::Result<Vec<umgen::generate::TokenGroups>> {
    use umgen::modality_agent::{ATTRIBUTES, AgentConfig};
    use umgen::scene::AgentCategory;
    let layout = registry.layout()?;
    let Some(seg) = layout
        .segments()
        .iter()
        .find(|s| s.kind == umgen::modality_agent::KIND)
    else {
        return Ok(Vec::new());
    };
    let table = bundle
        .config
        .modality
        .get(&seg.modality)
        .cloned()
        .unwrap_or_default();
    let cfg: AgentConfig = umgen::modality::parse_settings(&seg.modality, &table)?;
    let ids: Vec<u32> = AgentCategory::ALL.iter().map(|c| cfg.category_id(*c)).collect();
    let (lo, hi) = (
        ids.iter().min().copied().unwrap_or(0),
        ids.iter().max().copied().unwrap_or(0),
    );
    Ok(vec![umgen::generate::TokenGroups {
        first: seg.offset,
        size: ATTRIBUTES,
        count: seg.tokens / ATTRIBUTES,
        pad: cfg.pad_id(),
        values: cfg.bins,
        last: lo..hi + 1,
        // The official rule: the ego box (l 5.176 m, w 2.297 m) first, at most 30 other boxes.
        boxes: Some(umgen::generate::GroupBoxes {
            fields: [0, 1, 6, 7, 8].map(|i| {
                let [lo, hi] = cfg.ranges()[i];
                (i, lo, hi, cfg.bins)
            }),
            ego: [5.176, 2.297],
            max_boxes: 31,
        }),
    }])
}

/// Every agent-slot position whose token was not pad in a scene's newest frame: a pad drawn there is
/// redrawn from the TAR head, so agents leave the scene when the TAR says so, not on one OAR draw.
fn keep_agents(
    registry: &ModalityRegistry,
    history: &[Vec<Vec<u32>>],
) -> anyhow::Result<Vec<(usize, u32, Vec<bool>)>> {
    let layout = registry.layout()?;
    let Some(seg) = layout
        .segments()
        .iter()
        .find(|s| s.kind == umgen::modality_agent::KIND)
    else {
        return Ok(Vec::new());
    };
    let Some(pad) = seg.pad_id else {
        return Ok(Vec::new());
    };
    Ok((seg.offset..seg.offset + seg.tokens)
        .filter_map(|p| {
            let alive: Vec<bool> = history
                .iter()
                .map(|h| h.last().is_some_and(|f| f.get(p).is_some_and(|&id| id != pad)))
                .collect();
            alive.iter().any(|&x| x).then_some((p, pad, alive))
        })
        .collect())
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
