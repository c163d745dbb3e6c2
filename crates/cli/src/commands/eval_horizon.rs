//! The horizon part of `umgen eval`: per second generated, the rollouts' scene statistics
//! ([`umgen_eval::horizon`]) and the MMD of their agents per attribute group, each next to the real
//! split's, taken over every frame of its clips as the agent modality's slots hold them (the frames the
//! model was trained on), not from the ground truth of the continued clips.

use super::agents::agent_modality;
use super::eval::mmd_groups;
use super::eval_truth::decoded_agents;
use std::collections::HashMap;
use std::sync::Arc;
use umgen::data::Dataset;
use umgen::modality::ModalityRegistry;
use umgen::scene::{Agent, RoadNetwork, SceneClip};
use umgen_eval::horizon::{SceneStats, second_of};
use umgen_eval::offroad::Drivable;
use umgen_eval::targets::Check;

/// At most this many agents of each side enter an MMD (evenly spaced): its cost is the product of the two.
const MMD_AGENTS: usize = 1500;

/// Every `len / MMD_AGENTS`-th agent.
fn spaced<'a>(agents: &[&'a Agent]) -> Vec<&'a Agent> {
    let step = agents.len().div_ceil(MMD_AGENTS).max(1);
    agents.iter().step_by(step).copied().collect()
}

/// The drivable areas of road networks, each indexed once.
struct Maps<'a> {
    ds: &'a Dataset,
    by_network: HashMap<String, Arc<Drivable>>,
}

impl Maps<'_> {
    /// The drivable area of `network`.
    fn of(&mut self, network: &RoadNetwork) -> Arc<Drivable> {
        self.by_network
            .entry(network.id.clone())
            .or_insert_with(|| Arc::new(Drivable::new(network)))
            .clone()
    }

    /// The drivable area of the network of the dataset's clip `id`, if the dataset has it.
    fn of_clip(&mut self, id: &str) -> anyhow::Result<Option<Arc<Drivable>>> {
        let Some(net) = self.ds.clip_network_id(self.ds.find_clip(id)?) else {
            return Ok(None);
        };
        let network = self.ds.network(net)?;
        Ok(Some(self.of(&network)))
    }
}

/// `{"real": …, "seconds": [{"second", "frames", "generated", "mmd"}], "whole": {"frames", "generated",
/// "mmd"}}` (`whole`: every generated frame pooled, the horizon as one) for generated `scenes` whose scene
/// `s` continues `contexts[s / per]` of `ds` (none: scenes from scratch, whose maps are unknown), `dt`
/// seconds a frame, against `real` (the clips of the reference split, read with their networks); entries
/// and exits are told apart by whether they cross the agents' range (`extent`: x and y in the ego frame,
/// the agent modality's), where the bundle has one. With it, the rollout targets
/// ([`umgen_eval::targets::rollout`]) checked against these statistics.
#[allow(clippy::too_many_arguments)]
pub(super) fn horizon(
    scenes: &[SceneClip],
    contexts: &[serde_json::Value],
    per: usize,
    ds: &Dataset,
    registry: &ModalityRegistry,
    real: Vec<SceneClip>,
    dt: f64,
    extent: Option<[[f64; 2]; 2]>,
) -> anyhow::Result<(serde_json::Value, Vec<Check>)> {
    let mut maps = Maps {
        ds,
        by_network: HashMap::new(),
    };
    // The real split, every frame, agents as the slots hold them.
    let agent = agent_modality(registry)?.map(|(m, _)| m);
    let stats = || {
        let s = SceneStats::with_ego_box(umgen::EGO_BOX_M);
        match extent {
            Some([x, y]) => s.within(x, y),
            None => s,
        }
    };
    let mut real_stats = stats();
    let mut real_agents: Vec<Agent> = Vec::new();
    for mut clip in real {
        if let Some(m) = agent {
            let decoded = decoded_agents(m, &clip)?;
            for (f, agents) in clip.frames.iter_mut().zip(decoded) {
                f.agents = agents;
            }
        }
        let map = clip.network.as_deref().map(|n| maps.of(n));
        for (k, f) in clip.frames.iter().enumerate() {
            real_stats.add(f, &clip.frames[..k], clip.interval, map.as_deref());
        }
        real_agents.extend(clip.frames.iter().flat_map(|f| f.agents.iter().cloned()));
    }
    let real_refs: Vec<&Agent> = real_agents.iter().collect();
    // The rollouts, second by second.
    let mut seconds: Vec<(SceneStats, Vec<&Agent>)> = Vec::new();
    let (mut whole, mut whole_agents) = (stats(), Vec::<&Agent>::new());
    for (s, scene) in scenes.iter().enumerate() {
        let map = match contexts.get(s / per.max(1)).and_then(|c| c["clip"].as_str()) {
            Some(id) => maps.of_clip(id)?,
            None => None,
        };
        for (k, f) in scene.frames.iter().enumerate() {
            let second = second_of(k + 1, dt);
            if seconds.len() < second {
                seconds.resize_with(second, || (stats(), Vec::new()));
            }
            let (stats, agents) = &mut seconds[second - 1];
            let before = &scene.frames[..k];
            stats.add(f, before, dt, map.as_deref());
            agents.extend(f.agents.iter());
            whole.add(f, before, dt, map.as_deref());
            whole_agents.extend(f.agents.iter());
        }
    }
    let summaries: Vec<_> = seconds.iter().map(|(stats, _)| stats.summary()).collect();
    let rows: Vec<serde_json::Value> = summaries
        .iter()
        .zip(&seconds)
        .enumerate()
        .map(|(i, (summary, (_, agents)))| {
            serde_json::json!({
                "second": i + 1,
                "frames": summary.frames,
                "generated": summary,
                "mmd": mmd_groups(&spaced(agents), &spaced(&real_refs)),
            })
        })
        .collect();
    let (whole, real) = (whole.summary(), real_stats.summary());
    let checks = umgen_eval::targets::rollout(&real, &summaries, &whole);
    let json = serde_json::json!({
        "real": real,
        "seconds": rows,
        "whole": {
            "frames": whole.frames,
            "generated": whole,
            "mmd": mmd_groups(&spaced(&whole_agents), &spaced(&real_refs)),
        },
    });
    Ok((json, checks))
}
