//! Scene clips (e.g. generated rollouts) written back as a umgen dataset, so that every dataset tool
//! (`umgen data info`, `umgen viz --data`, tokenizing, evaluation against real data) reads them unchanged.

use crate::error::{DataError, Result, corrupt, io};
use crate::index::{ClipEntry, Index, LogEntry, NetworkEntry};
use crate::log::{Log, State, Track, write_atomic};
use crate::stats::clip_stats;
use crate::sumo::class_defaults;
use crate::view::ViewOptions;
use std::collections::BTreeMap;
use std::path::Path;
use umgen_scene::{AgentCategory, RoadNetwork, SceneClip};

/// The class a written track gets for its category (the dataset's tracks carry a SUMO-style class).
fn class_of(c: AgentCategory) -> &'static str {
    match c {
        AgentCategory::Vehicle => "passenger",
        AgentCategory::Pedestrian => "pedestrian",
        AgentCategory::Cyclist => "bicycle",
    }
}

/// One clip as a log: the ego is track 0 (a passenger car's size), every other `track_id` seen in the clip
/// becomes a track in order of first appearance with the size and category it first had; positions and
/// headings go back to world coordinates through the ego pose, speed is the length of the velocity.
pub fn clip_log(clip: &SceneClip) -> Log {
    let (length, width, height) = class_defaults("passenger");
    let mut tracks = vec![Track {
        name: "ego".into(),
        category: AgentCategory::Vehicle,
        class: "passenger".into(),
        length,
        width,
        height,
    }];
    let mut ids: BTreeMap<u64, u32> = BTreeMap::new();
    let mut steps = Vec::with_capacity(clip.frames.len());
    for f in &clip.frames {
        let ego = f.ego.pose2();
        let mut step = vec![State {
            track: 0,
            x: f.ego.x as f32,
            y: f.ego.y as f32,
            heading: f.ego.heading as f32,
            speed: f.ego.speed as f32,
        }];
        for a in &f.agents {
            let track = *ids.entry(a.track_id).or_insert_with(|| {
                tracks.push(Track {
                    name: format!("agent-{}", a.track_id),
                    category: a.category,
                    class: class_of(a.category).into(),
                    length: a.length,
                    width: a.width,
                    height: a.height,
                });
                (tracks.len() - 1) as u32
            });
            let [x, y] = ego.to_parent([a.x, a.y]);
            step.push(State {
                track,
                x: x as f32,
                y: y as f32,
                heading: umgen_scene::wrap_angle(a.heading + ego.heading) as f32,
                speed: a.vx.hypot(a.vy) as f32,
            });
        }
        // Readers find a track in a step by binary search; one state per track and step.
        step.sort_by_key(|s| s.track);
        step.dedup_by_key(|s| s.track);
        steps.push(step);
    }
    Log {
        tracks,
        t0: 0.0,
        dt: clip.interval,
        steps,
    }
}

/// Writes `clips` as a new dataset in `out` (which must not hold one yet): one log and one clip per scene
/// clip, ids `<prefix>-<k>`, all in `split`; the road network of each clip (an empty one named `none`
/// where a clip has none). Returns the index written.
pub fn write_scene_dataset(out: &Path, clips: &[SceneClip], prefix: &str, split: &str) -> Result<Index> {
    let request = |message: String| DataError::Request {
        path: out.into(),
        message,
    };
    if out.join(crate::index::INDEX_FILE).exists() {
        return Err(request("already holds a dataset".into()));
    }
    let interval = clips.first().map_or(0.5, |c| c.interval);
    if let Some(c) = clips.iter().find(|c| (c.interval - interval).abs() > 1e-9) {
        return Err(request(format!(
            "clip `{}` steps every {} s, the others every {interval} s",
            c.id, c.interval
        )));
    }
    if let Some(c) = clips.iter().find(|c| c.frames.is_empty()) {
        return Err(request(format!("clip `{}` has no frames", c.id)));
    }
    for dir in ["logs", "networks"] {
        std::fs::create_dir_all(out.join(dir)).map_err(io(out.join(dir)))?;
    }
    let mut index = Index::new(interval);
    let empty = RoadNetwork {
        id: "none".into(),
        ..RoadNetwork::default()
    };
    for (k, clip) in clips.iter().enumerate() {
        let net = clip.network.as_deref().unwrap_or(&empty);
        if !index.networks.iter().any(|n| n.id == net.id) {
            let file = format!("networks/{}.json", net.id);
            let json = serde_json::to_vec(net).map_err(|e| corrupt(out.join(&file), e.to_string()))?;
            write_atomic(&out.join(&file), &json)?;
            index.networks.push(NetworkEntry {
                id: net.id.clone(),
                file,
                crc32: crc32fast::hash(&json),
                elements: net.element_count(),
            });
        }
        let id = format!("{prefix}-{k}");
        let log = clip_log(clip);
        let file = format!("logs/{id}.ulog");
        let entry = ClipEntry {
            id: format!("{id}/ego:0"),
            log: id.clone(),
            ego_track: 0,
            first_step: 0,
            frames: log.steps.len(),
            split: split.into(),
        };
        let stats = clip_stats(
            &log,
            std::slice::from_ref(&entry),
            &ViewOptions::default(),
            &out.join(&file),
        )?;
        log.write(&out.join(&file))?;
        index.stats.merge(&stats);
        index.logs.push(LogEntry {
            id,
            network: net.id.clone(),
            file,
            source: format!("scenes: {}", clip.id),
            steps: log.steps.len(),
            tracks: log.tracks.len(),
            split: split.into(),
            stats,
            signals: None,
        });
        index.clips.push(entry);
    }
    index.check(&out.join(crate::index::INDEX_FILE))?;
    index.save(out)?;
    Ok(index)
}
