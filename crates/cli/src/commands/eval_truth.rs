//! What the real data did after each context of a `generate` output: the truth `umgen eval` compares the
//! model and the kinematic baselines with, decoded through the bundle's agent tokenizer.

use super::agents::agent_modality;
use anyhow::Context;
use umgen::data::Dataset;
use umgen::modality::{Modality, ModalityRegistry};
use umgen::modality_agent::{ATTRIBUTES, SlotPlan};
use umgen::scene::{Agent, Frame, SceneClip};
use umgen_eval::l2::{constant_velocity_ego, ego_l2};

/// Agents of every frame of `clip` as the model's agent tokens decode them (slot ids as track ids, binned
/// values). Only the agent modality runs: the map and image tokenizers are not needed here, and on a CPU
/// their encoders take seconds per frame.
pub(super) fn decoded_agents(agent: &dyn Modality, clip: &SceneClip) -> anyhow::Result<Vec<Vec<Agent>>> {
    agent
        .tokenize_clip(clip)?
        .iter()
        .map(|ids| {
            let mut f = Frame::default();
            agent.detokenize(ids, &mut f)?;
            Ok(f.agents)
        })
        .collect()
}

/// `clip` with only the tracks that the slot plan of its first `n` frames keeps, in every frame, and that
/// plan. Generation tokenized those `n` context frames alone, so their slots are the generated scene's;
/// tokenizing the whole clip instead would give tracks first seen after the context slots of their own
/// (which the model's new agents would then be compared with) and, in crowded clips, keep other tracks.
fn context_tracks_only(clip: &SceneClip, n: usize, slots: usize) -> anyhow::Result<(SceneClip, SlotPlan)> {
    let mut context = clip.clone();
    context.frames.truncate(n);
    let plan = SlotPlan::new(&context, slots)?;
    let mut out = clip.clone();
    for f in &mut out.frames {
        f.agents.retain(|a| plan.slot(a.track_id).is_some());
    }
    Ok((out, plan))
}

/// A frame's agents as recorded (unbinned), with their slots of `plan` as track ids: the decoded agents'
/// ids, so that a prediction from the real state is matched with the same truth.
fn real_in_slots(f: &Frame, plan: &SlotPlan) -> Vec<Agent> {
    f.agents
        .iter()
        .filter_map(|a| {
            plan.slot(a.track_id).map(|s| Agent {
                track_id: s as u64,
                ..*a
            })
        })
        .collect()
}

/// What a context clip really did after its context frames.
pub(super) struct Truth {
    /// The last context frame.
    pub(super) last: Frame,
    /// Its agents as the bundle's tokens decode them (slot ids as track ids).
    pub(super) last_agents: Vec<Agent>,
    /// The context frame before it (ego pose and decoded agents), for the constant-acceleration baseline;
    /// `None` for a one-frame context.
    pub(super) before: Option<(umgen::scene::EgoPose, Vec<Agent>)>,
    /// The last two context frames' agents as recorded, unbinned (slot ids as track ids; the first
    /// empty for a one-frame context): what constant acceleration does knowing the real state exactly,
    /// the most a kinematic rule can take from the present.
    pub(super) real_state: [Vec<Agent>; 2],
    /// Real ego poses of the following frames.
    pub(super) poses: Vec<umgen::scene::EgoPose>,
    /// Real agents of the following frames, decoded like `last_agents`: the context's tracks in the
    /// context's slots, for position errors.
    pub(super) tracked: Vec<Vec<Agent>>,
    /// Every real agent of the following frames (decoded), for MMD.
    pub(super) agents: Vec<Vec<Agent>>,
    /// Constant-velocity ego error at each following frame.
    pub(super) cv_ego: Vec<f64>,
}

/// The ground truth of `context` (`{"clip", "frames"}` of meta.json) for up to `k` frames after it.
pub(super) fn ground_truth(
    ds: &Dataset,
    registry: &ModalityRegistry,
    context: &serde_json::Value,
    k: usize,
    dt: f64,
) -> anyhow::Result<Truth> {
    let clip_id = context["clip"].as_str().context("meta.json: contexts[].clip")?;
    let n = context["frames"].as_u64().unwrap_or(1) as usize;
    let idx = ds.find_clip(clip_id)?;
    let k = k.min(ds.clips()[idx].frames.saturating_sub(n));
    anyhow::ensure!(
        n >= 1 && k >= 1,
        "clip `{clip_id}` has no ground truth after its {n} context frames"
    );
    let gt = ds.read_window(idx, 0, n + k, 1)?;
    let (mut tracked, agents, real_state) = match agent_modality(registry)? {
        Some((m, seg)) => {
            let slots = seg.tokens / ATTRIBUTES;
            let mut all = decoded_agents(m, &gt)?;
            let (kept, plan) = context_tracks_only(&gt, n, slots)?;
            let real = |i: Option<usize>| i.map_or_else(Vec::new, |i| real_in_slots(&gt.frames[i], &plan));
            (
                decoded_agents(m, &kept)?,
                all.split_off(n),
                [real(n.checked_sub(2)), real(Some(n - 1))],
            )
        }
        None => (vec![Vec::new(); n + k], vec![Vec::new(); k], Default::default()),
    };
    let future = tracked.split_off(n);
    let last_agents = tracked.pop().unwrap_or_default();
    let before = (n >= 2).then(|| (gt.frames[n - 2].ego, tracked.pop().unwrap_or_default()));
    let last = gt.frames[n - 1].clone();
    let poses: Vec<_> = gt.frames[n..n + k].iter().map(|f| f.ego).collect();
    let cv_ego = ego_l2(&constant_velocity_ego(&last.ego, &last.action, dt, k), &poses);
    Ok(Truth {
        last_agents,
        before,
        real_state,
        last,
        poses,
        tracked: future,
        agents,
        cv_ego,
    })
}

#[cfg(test)]
pub(super) mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use umgen::scene::AgentCategory;

    pub(in crate::commands) fn at(track_id: u64, x: f64) -> Agent {
        Agent {
            track_id,
            category: AgentCategory::Vehicle,
            x,
            y: 0.0,
            z: 0.0,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
            heading: 0.0,
            length: 4.0,
            width: 2.0,
            height: 1.5,
        }
    }

    fn clip(frames: Vec<Vec<Agent>>) -> SceneClip {
        let frames = frames
            .into_iter()
            .enumerate()
            .map(|(t, agents)| Frame {
                time: 0.5 * t as f64,
                agents,
                ..Frame::default()
            })
            .collect();
        SceneClip::new("c", 0.5, frames).unwrap()
    }

    fn tracks(c: &SceneClip) -> Vec<Vec<u64>> {
        c.frames
            .iter()
            .map(|f| f.agents.iter().map(|a| a.track_id).collect())
            .collect()
    }

    #[test]
    fn ground_truth_keeps_the_context_tracks_in_their_slots() {
        // Two context frames with tracks 7 (20 m) and 3 (10 m); track 9 appears after the context; track 7
        // comes to 1 m after it.
        let gt = clip(vec![
            vec![at(7, 20.0), at(3, 10.0)],
            vec![at(7, 20.0), at(3, 10.0)],
            vec![at(7, 1.0), at(3, 10.0), at(9, 5.0)],
        ]);
        // The new track goes: the model's new agents have no real identity to be compared with.
        assert_eq!(tracks(&context_tracks_only(&gt, 2, 4).unwrap().0)[2], vec![7, 3]);
        // One slot: the context keeps track 3 (nearest in the context), the whole clip would keep track 7
        // (nearest over all frames). The context's choice holds in every frame.
        let (one, one_plan) = context_tracks_only(&gt, 2, 1).unwrap();
        assert_eq!(tracks(&one), vec![vec![3], vec![3], vec![3]]);
        // The recorded agents of a frame, by the same slots, values untouched (10.03 m is not a bin
        // centre of the 0.125 m bins).
        let mut moved = gt.frames[2].clone();
        moved.agents[1].x = 10.03;
        let real = real_in_slots(&moved, &one_plan);
        assert_eq!(real.len(), 1);
        assert_eq!((real[0].track_id, real[0].x), (0, 10.03));
        assert_eq!(SlotPlan::new(&gt, 1).unwrap().slot(7), Some(0));
        // Tokenized alone, the restricted clip gives the context's slots.
        let context = SceneClip::new("c", 0.5, gt.frames[..2].to_vec()).unwrap();
        let (plan, whole) = (
            SlotPlan::new(&context, 4).unwrap(),
            SlotPlan::new(&gt, 4).unwrap(),
        );
        let kept = SlotPlan::new(&context_tracks_only(&gt, 2, 4).unwrap().0, 4).unwrap();
        for track in [7, 3] {
            assert_eq!(kept.slot(track), plan.slot(track));
            assert_eq!(whole.slot(track), plan.slot(track));
        }
        assert_eq!((kept.slot(9), whole.slot(9)), (None, Some(2)));
    }
}
