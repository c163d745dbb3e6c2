//! `umgen generate`: roll a bundle's model forward from a dataset clip or from nothing, decode the frames
//! and draw them.

use super::contexts::context_clips;
use crate::cli::GenerateArgs;
use crate::device::Device;
use anyhow::Context;
use std::path::Path;
use umgen::backbone::Backbone;
use umgen::checkpoint::burn_io::weights_from_bytes;
use umgen::generate::engine::EngineSettings;
use umgen::generate::{Control, Generator, NextFrame, Sampling};
use umgen::scene::SceneClip;
use umgen::{Bundle, backbone_spec};

/// Generates.
pub fn run(a: &GenerateArgs, kinds: &crate::Kinds) -> anyhow::Result<()> {
    anyhow::ensure!(a.scenes >= 1, "--scenes must be at least 1");
    let device = Device::parse(&a.device)?;
    let (bundle, registry) = Bundle::open_with(&a.bundle, &kinds.catalog_with(device.codec_loader())?)?;
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
    let window = history_window(a.window, &bundle.config);
    let (contexts, interval) = context_clips(a, window)?;
    let step_s = bundle.config.backbone.step_s;
    // Scenes from scratch step as the model was trained to.
    let interval = if contexts.is_empty() { step_s } else { interval };
    if let Some(k) = &spec.track {
        anyhow::ensure!(
            k.steps_by(interval),
            "the contexts' frames are {interval} s apart, but the model moves its tracked slots by \
             backbone.step_s = {} s (what it was trained on)",
            k.step_s
        );
    }
    let context_rows = contexts
        .iter()
        .map(|c| registry.tokenize_clip(&c.clip))
        .collect::<Result<Vec<_>, _>>()?;
    let recorded = super::recorded::modalities(a, &contexts, &context_rows, &control, &registry, &spec)?;
    // Scene s continues context s / --scenes (each context's scenes are consecutive).
    let total = a.scenes * contexts.len().max(1);
    let context_of = |s: usize| (!contexts.is_empty()).then_some(s / a.scenes);
    let sampling = Sampling {
        top_k: a.top_k,
        top_p: a.top_p,
        temperature: a.temperature,
        top_p_rest: false,
    };
    let labels: Vec<&str> = spec.segments.iter().map(|s| s.label.as_str()).collect();
    let samplings = sampling.per_segment(&a.top_k_of, &a.top_p_of, &a.top_p_rest_of, &labels)?;
    // Recorded in meta.json: what each modality was drawn with.
    let sampling_meta: serde_json::Map<String, serde_json::Value> = labels
        .iter()
        .zip(&samplings)
        .map(|(l, s)| Ok((l.to_string(), serde_json::to_value(s)?)))
        .collect::<Result<_, serde_json::Error>>()?;
    let bins = spec.action.as_ref().map(|x| x.bins);
    let agents = super::agents::AgentSlots::of(&bundle, &registry)?;
    let control = applicable_control(a, control, bins.is_some(), agents.as_ref().map(|s| s.slots()))?;
    let whole_frame = a.new_agent_rule == crate::cli::NewAgentRule::Frame;
    let rule = if whole_frame { "frame" } else { "before" };
    let groups: Vec<_> = agents
        .iter()
        .map(|s| {
            let mut g = s.groups();
            if let Some(b) = g.boxes.as_mut() {
                b.whole_frame = whole_frame;
            }
            g
        })
        .collect();
    let road = match (a.entering_on_road, agents.as_ref()) {
        (false, _) => None,
        (true, None) => {
            anyhow::bail!("--entering-on-road tests entering agents, and this model has no agent modality")
        }
        (true, Some(slots)) => {
            let layout = registry.layout()?;
            anyhow::ensure!(
                !recorded
                    .iter()
                    .any(|r| layout.segments()[r.segment].kind == umgen::modality_agent::KIND),
                "--entering-on-road tests the agents the model draws; with the agents recorded it draws none"
            );
            Some(super::road::RoadCheck::new(
                &bundle,
                &registry,
                &slots.groups(),
                slots.vehicle_id(),
            )?)
        }
    };
    let cuda = matches!(device, Device::Cuda(_));
    let on_device = a.draw.on_device(cuda, total);
    let engine = a.decoder.engine(cuda);
    anyhow::ensure!(
        !(engine && a.speculate > 0),
        "--speculate decodes with the burn model: add --decoder burn"
    );
    let plan = super::generate_plan::Plan {
        a,
        control: &control,
        bins,
        agents: &agents,
        recorded: &recorded,
        action_segment: spec.action.as_ref().map(|x| x.segment),
        groups: &groups,
        road: road.as_ref(),
    };
    let mut hold = match a.map_memory {
        true => Some(super::map_memory::MapHold::new(
            &bundle,
            &registry,
            plan.action_segment,
            &recorded.iter().map(|r| r.segment).collect::<Vec<_>>(),
            &contexts,
            &context_rows,
            total,
            context_of,
            interval,
        )?),
        false => None,
    };
    let mut history: Vec<Vec<Vec<u32>>> = (0..total)
        .map(|s| context_of(s).map_or_else(Vec::new, |c| context_rows[c].clone()))
        .collect();
    let started = std::time::Instant::now();
    let ((new_tested, new_dropped), (road_count, first_draws)) = if engine {
        // The weights go to the engine's own buffers: the burn model that reads the bundle stays on the CPU.
        let cfg = bundle.config.backbone.for_inference();
        let model = Backbone::<burn::backend::Flex>::new(&cfg, &spec, &Default::default())?;
        let model = weights_from_bytes(model, bundle.weights_f32()?, "bundle weights")?;
        let settings = EngineSettings {
            sampling: samplings,
            window,
            seed: a.seed,
            pass_frames: a.pass_frames,
        };
        let mut e = super::engine::AnyEngine::new(device, &model.plain(), settings, a.precision)?;
        drop(model);
        let road = plan.roll_out(&mut e, &mut history, hold.as_mut())?;
        (e.new_agents(), road)
    } else {
        crate::with_inference!(device, |I, dev| {
            let model = Backbone::<I>::new(&bundle.config.backbone.for_inference(), &spec, &dev)?;
            let model = weights_from_bytes(model, bundle.weights_f32()?, "bundle weights")?;
            let mut g = Generator::new(&model, samplings, window, a.seed)?
                .draw_on_device(on_device)
                .pass_frames(a.pass_frames)
                .device_top_k(a.device_top_k.into())
                .speculate(a.speculate);
            let road = plan.roll_out(&mut g, &mut history, hold.as_mut())?;
            let (blocks, decided) = g.speculation();
            if blocks > 0 {
                tracing::info!(
                    "speculative decoding: {blocks} blocks decided {decided} positions ({:.2} per OAR pass)",
                    decided as f64 / blocks as f64
                );
            }
            (g.new_agents(), road)
        })
    };
    // The first draws of held frames were drawn again: count the new agents of the frames kept.
    let (new_tested, new_dropped) = (new_tested - first_draws.0, new_dropped - first_draws.1);
    let held = hold.as_ref().map(|h| h.count());
    if let Some(c) = held {
        tracing::info!(
            "map memory: {:.1} % of the generated frames' map held, {:.1} % of their map codes changed from \
             the first draw",
            100.0 * c.held as f64 / c.pixels.max(1) as f64,
            100.0 * c.changed as f64 / c.codes.max(1) as f64
        );
    }
    if new_tested > 0 {
        tracing::info!(
            "new-agent rule ({rule}): dropped {new_dropped} of {new_tested} new agents (overlapping {}, or over \
             the frame's box budget)",
            if whole_frame {
                "a box decoded before them or an old agent after them"
            } else {
                "a box decoded before them"
            }
        );
    }
    if road.is_some() {
        tracing::info!(
            "road rule: emptied {} of {} entering vehicles off their frame's own drivable map ({} beyond \
             the map's raster, kept)",
            road_count.dropped,
            road_count.tested,
            road_count.beyond
        );
    }
    let scenes = history;
    let elapsed = started.elapsed().as_secs_f64();
    let n_context = context_rows.first().map_or(0, Vec::len);
    // Fewer than --frames when --time-limit stopped the rollout.
    let frames = scenes.first().map_or(0, |s| s.len().saturating_sub(n_context));
    let tokens = (frames * total * spec.n) as f64;
    tracing::info!(
        "generated {frames} frame(s) × {} scene(s) in {elapsed:.1} s ({:.0} tokens/s, {:.2} frames/s)",
        total,
        tokens / elapsed,
        (frames * total) as f64 / elapsed
    );
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let context_index: Vec<Option<usize>> = (0..total).map(context_of).collect();
    std::fs::write(
        a.out.join("tokens.json"),
        serde_json::to_vec(&serde_json::json!({
            "n": spec.n, "context_frames": n_context, "fingerprint": bundle.manifest.fingerprint,
            "context_of": context_index, "scenes": scenes,
        }))?,
    )?;
    // scenes.json and dataset/ hold no map or camera rasters: only scene 0, drawn into rollout.gif,
    // runs their VQ decoders.
    let starts: Vec<super::scenes::Start> = contexts
        .iter()
        .map(|c| {
            (
                c.clip.frames.last().cloned().unwrap_or_default(),
                c.clip.network.clone(),
            )
        })
        .collect();
    let decoded = super::scenes::decode_rollout(
        &registry,
        &scenes,
        n_context,
        interval,
        (&context_index, &starts),
        |s| if s == 0 { &[] } else { super::scenes::RASTERS },
    )?;
    let light: Vec<SceneClip> = decoded
        .iter()
        .map(|c| {
            let mut c = c.clone();
            c.frames.iter_mut().for_each(|f| (f.map, f.image) = (None, None));
            c
        })
        .collect();
    std::fs::write(a.out.join("scenes.json"), serde_json::to_vec(&light)?)?;
    write_dataset(&a.out.join("dataset"), light)?;
    // What `umgen eval` needs to find the ground truth and the tokenizers.
    let context_meta: Vec<serde_json::Value> = contexts
        .iter()
        .map(|c| serde_json::json!({"data": c.data, "clip": c.id, "frames": n_context}))
        .collect();
    let recorded_labels: Vec<&str> = recorded
        .iter()
        .map(|r| spec.segments[r.segment].label.as_str())
        .collect();
    let recorded_ego = recorded.iter().any(|r| Some(r.segment) == plan.action_segment);
    std::fs::write(
        a.out.join("meta.json"),
        serde_json::to_vec_pretty(&serde_json::json!({
            "bundle": std::fs::canonicalize(&a.bundle).unwrap_or_else(|_| a.bundle.clone()),
            "contexts": context_meta,
            "frames": frames,
            "scenes": total,
            "scenes_per_context": a.scenes,
            "seed": a.seed,
            "sampling": sampling_meta,
            // The draws of a seed depend on it (their distribution does not).
            "speculate": a.speculate,
            "decoder": if engine { "engine" } else { "burn" },
            "draw": if engine { "engine" } else if on_device { "device" } else { "host" },
            "new_agents": {"tested": new_tested, "dropped": new_dropped, "rule": rule},
            "entering_on_road": road.as_ref().map(|_| serde_json::json!({
                "tested": road_count.tested, "dropped": road_count.dropped, "beyond_map": road_count.beyond,
            })),
            "map_memory": held.map(|c| serde_json::json!({
                "frames": c.frames, "pixels": c.pixels, "held": c.held, "codes": c.codes,
                "changed_from_first_draw": c.changed,
            })),
            "interval": interval,
            "recorded_ego": recorded_ego,
            "recorded": recorded_labels,
        }))?,
    )?;
    super::scenes::draw(
        &bundle,
        &registry,
        &decoded[0],
        &a.out.join("rollout.gif"),
        a.png.then_some(a.out.as_path()),
        0,
    )?;
    tracing::info!(
        "{}: tokens.json, scenes.json, dataset/, rollout.gif ({} context + {} generated frames)",
        a.out.display(),
        n_context,
        frames
    );
    Ok(())
}

/// The decoded scenes as a umgen dataset in `dir` (replacing one from an earlier run), each on its context
/// clip's road network: ego and agent tracks in world coordinates, one clip per scene, split `generated`.
/// Generated map and image tokens are not part of it (a dataset derives those from its network).
fn write_dataset(dir: &Path, scenes: Vec<SceneClip>) -> anyhow::Result<()> {
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

/// The entries of `control` that can apply to this rollout; entries that cannot, in whole or in part, are
/// an error naming the file and each entry, or with `--allow-partial-control` a warning each.
fn applicable_control(
    a: &GenerateArgs,
    control: Control,
    ego_action: bool,
    agent_slots: Option<usize>,
) -> anyhow::Result<Control> {
    let (kept, problems) = control.applicable(a.frames, ego_action, agent_slots);
    let Some(file) = a.control.as_ref().filter(|_| !problems.is_empty()) else {
        return Ok(kept);
    };
    anyhow::ensure!(
        a.allow_partial_control,
        "{}: {} control entr(ies) cannot apply to {} generated frame(s) of this model: {} \
         (--allow-partial-control generates with the rest)",
        file.display(),
        problems.len(),
        a.frames,
        problems.join("; ")
    );
    for p in &problems {
        tracing::warn!("{}: {p}; generating without it", file.display());
    }
    Ok(kept)
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

/// The frames of history the TAR sees: `--window`, else the longest history the model was trained on
/// (`train.frames`; its time embeddings past that never received a gradient), at most the paper's 20 and
/// `backbone.max_frames`.
fn history_window(asked: Option<usize>, config: &umgen::UmgenConfig) -> usize {
    asked.unwrap_or_else(|| {
        let w = umgen::history_window(config);
        if w < 20 {
            tracing::info!(
                "conditioning on at most {w} frames (the history the model was trained on; --window to change)"
            );
        }
        w
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::history_window;
    use umgen::UmgenConfig;

    #[test]
    fn the_default_window_is_the_trained_history() {
        let config = |frames: usize, max_frames: usize| {
            let text = format!(
                "[layout]\norder = [\"ego\"]\n[backbone]\nmax_frames = {max_frames}\n[train]\nframes = {frames}\n"
            );
            UmgenConfig::from_toml_str(&text).unwrap()
        };
        // Trained on 8 frames of history: later time embeddings never learned anything.
        assert_eq!(history_window(None, &config(8, 32)), 8);
        // The paper's 20 at most, and never past the model's time embeddings.
        assert_eq!(history_window(None, &config(24, 32)), 20);
        assert_eq!(history_window(None, &config(16, 12)), 12);
        // An explicit --window wins.
        assert_eq!(history_window(Some(3), &config(8, 32)), 3);
    }
}
