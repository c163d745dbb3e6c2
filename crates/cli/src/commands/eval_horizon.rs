//! The horizon part of `umgen eval`: per second generated, the rollouts' scene statistics
//! ([`umgen_eval::horizon`]) and the MMD of their agents per attribute group, each next to the real
//! split's, taken over every frame of its clips as the agent modality's slots hold them (the frames the
//! model was trained on), not from the ground truth of the continued clips.

use super::agents::agent_modality;
use super::eval_truth::decoded_agents;
use std::collections::HashMap;
use std::sync::Arc;
use umgen::data::Dataset;
use umgen::modality::ModalityRegistry;
use umgen::scene::{Agent, SceneClip};
use umgen_eval::horizon::{SceneStats, second_of};
use umgen_eval::mmd::{Group, mmd};
use umgen_eval::offroad::Drivable;

/// At most this many agents of each side enter an MMD (evenly spaced): its cost is the product of the two.
const MMD_AGENTS: usize = 1500;

/// Every `len / MMD_AGENTS`-th agent.
fn spaced<'a>(agents: &[&'a Agent]) -> Vec<&'a Agent> {
    let step = agents.len().div_ceil(MMD_AGENTS).max(1);
    agents.iter().step_by(step).copied().collect()
}

/// MMD per attribute group.
fn mmd_groups(generated: &[&Agent], real: &[&Agent]) -> serde_json::Value {
    let (x, y) = (spaced(generated), spaced(real));
    let mut out = serde_json::Map::new();
    for g in Group::ALL {
        let fx: Vec<Vec<f64>> = x.iter().map(|a| g.features(a)).collect();
        let fy: Vec<Vec<f64>> = y.iter().map(|a| g.features(a)).collect();
        out.insert(g.name().into(), serde_json::json!(mmd(&fx, &fy)));
    }
    serde_json::Value::Object(out)
}

/// Road networks by clip id, each indexed once.
struct Maps<'a> {
    ds: &'a Dataset,
    by_network: HashMap<String, Arc<Drivable>>,
}

impl Maps<'_> {
    /// The drivable area of clip `index`'s network, if the dataset has it.
    fn of(&mut self, index: usize) -> anyhow::Result<Option<Arc<Drivable>>> {
        let log = &self.ds.clips()[index].log;
        let Some(id) = self
            .ds
            .index()
            .logs
            .iter()
            .find(|l| &l.id == log)
            .map(|l| l.network.as_str())
        else {
            return Ok(None);
        };
        if let Some(d) = self.by_network.get(id) {
            return Ok(Some(d.clone()));
        }
        let d = Arc::new(Drivable::new(self.ds.network(id)?.as_ref()));
        self.by_network.insert(id.to_string(), d.clone());
        Ok(Some(d))
    }
}

/// `{"real": …, "seconds": [{"second", "frames", "generated", "mmd"}]}` for generated `scenes` whose scene
/// `s` continues `contexts[s / per]` (none: scenes from scratch, whose maps are unknown), `dt` seconds a
/// frame, against the clips of `split` in `ds`.
pub(super) fn horizon(
    scenes: &[SceneClip],
    contexts: &[serde_json::Value],
    per: usize,
    ds: &Dataset,
    registry: &ModalityRegistry,
    split: &str,
    dt: f64,
) -> anyhow::Result<serde_json::Value> {
    let mut maps = Maps {
        ds,
        by_network: HashMap::new(),
    };
    // The real split, every frame, agents as the slots hold them.
    let agent = agent_modality(registry)?.map(|(m, _)| m);
    let mut real = SceneStats::default();
    let mut real_agents: Vec<Agent> = Vec::new();
    for i in (0..ds.clips().len()).filter(|&i| ds.clips()[i].split == split) {
        let mut clip = ds.read_clip(i)?;
        if let Some(m) = agent {
            let decoded = decoded_agents(m, &clip)?;
            for (f, agents) in clip.frames.iter_mut().zip(decoded) {
                f.agents = agents;
            }
        }
        let map = maps.of(i)?;
        for (k, f) in clip.frames.iter().enumerate() {
            let before = k.checked_sub(1).map(|j| &clip.frames[j]);
            real.add(f, before, clip.interval, map.as_deref());
        }
        real_agents.extend(clip.frames.iter().flat_map(|f| f.agents.iter().cloned()));
    }
    let real_refs: Vec<&Agent> = real_agents.iter().collect();
    // The rollouts, second by second.
    let mut seconds: Vec<(SceneStats, Vec<&Agent>)> = Vec::new();
    for (s, scene) in scenes.iter().enumerate() {
        let map = match contexts.get(s / per.max(1)).and_then(|c| c["clip"].as_str()) {
            Some(id) => maps.of(ds.find_clip(id)?)?,
            None => None,
        };
        for (k, f) in scene.frames.iter().enumerate() {
            let second = second_of(k + 1, dt);
            if seconds.len() < second {
                seconds.resize_with(second, Default::default);
            }
            let (stats, agents) = &mut seconds[second - 1];
            stats.add(f, k.checked_sub(1).map(|j| &scene.frames[j]), dt, map.as_deref());
            agents.extend(f.agents.iter());
        }
    }
    let rows: Vec<serde_json::Value> = seconds
        .iter()
        .enumerate()
        .map(|(i, (stats, agents))| {
            let summary = stats.summary();
            serde_json::json!({
                "second": i + 1,
                "frames": summary.frames,
                "generated": summary,
                "mmd": mmd_groups(agents, &real_refs),
            })
        })
        .collect();
    Ok(serde_json::json!({"real": real.summary(), "seconds": rows}))
}
