//! What `umgen generate` imposes on each frame of a rollout (the control file, the recorded or forced ego
//! actions, the agent slots' rules) and the loop that asks a decoder for the frames.

use crate::cli::GenerateArgs;
use umgen::generate::{Control, FrameControl, GivenSegment, NextFrame, RoadCount};

/// What a rollout imposes on each frame: the control file, the recorded or forced ego actions, the agent
/// slots' rules.
pub(super) struct Plan<'a> {
    pub(super) a: &'a GenerateArgs,
    pub(super) control: &'a Control,
    pub(super) bins: Option<[(f64, f64, u32); 3]>,
    pub(super) agents: &'a Option<super::agents::AgentSlots>,
    pub(super) recorded: &'a [super::recorded::Recorded],
    /// The ego action's segment: a recorded one replaces the ego module's action.
    pub(super) action_segment: Option<usize>,
    pub(super) groups: &'a [umgen::generate::TokenGroups],
    /// The road rule for entering vehicles (`--entering-on-road`).
    pub(super) road: Option<&'a super::road::RoadCheck<'a>>,
}

impl Plan<'_> {
    /// Generates `--frames` frames onto every scene's `history` with `g` (fewer when `--time-limit` stops
    /// it), a progress bar or a log line per frame, each frame drawn a second time on its held map where
    /// `hold` holds the maps; what the road rule did, if it ran, and the new agents that `g` tested and
    /// dropped in first draws (which its own count includes).
    pub(super) fn roll_out(
        &self,
        g: &mut dyn NextFrame,
        history: &mut [Vec<Vec<u32>>],
        mut hold: Option<&mut super::map_memory::MapHold<'_>>,
    ) -> anyhow::Result<(RoadCount, (u64, u64))> {
        let mut road = RoadCount::default();
        let mut first_draws = (0, 0);
        let (a, control) = (self.a, self.control);
        let total = history.len();
        let bar = crate::progress::bar(a.frames as u64, "frames")?;
        let limit = crate::progress::TimeLimit::minutes(a.time_limit);
        for k in 0..a.frames {
            if k > 0 && limit.reached(&bar, k as u64) {
                tracing::warn!(
                    "time limit: {k} of {} frame(s) generated; writing those",
                    a.frames
                );
                break;
            }
            let forced = self.bins.and_then(|b| control.action_at(k, &b));
            if let Some((_, clamped)) = &forced
                && *clamped > 0
            {
                tracing::warn!("frame {k}: {clamped} forced action value(s) outside the bins, clamped");
            }
            let ((placed, below), keep) = match self.agents {
                Some(slots) => (slots.placement(control, k)?, slots.keep(history)),
                None => {
                    anyhow::ensure!(
                        control.agents_at(k).next().is_none(),
                        "the control file sets agents, but this model has no agent modality"
                    );
                    Default::default()
                }
            };
            let per_scene = |r: &super::recorded::Recorded| -> Vec<Vec<u32>> {
                (0..total).map(|s| r.blocks[s / a.scenes][k].clone()).collect()
            };
            let action_segment = self.action_segment;
            let action = match self.recorded.iter().find(|r| Some(r.segment) == action_segment) {
                Some(r) => Some(per_scene(r)),
                None => forced.map(|(ids, _)| vec![ids; total]),
            };
            let given = self
                .recorded
                .iter()
                .filter(|r| Some(r.segment) != action_segment)
                .map(|r| GivenSegment {
                    segment: r.segment,
                    ids: per_scene(r),
                })
                .collect();
            let fc = FrameControl {
                action,
                tokens: placed,
                below,
                keep,
                groups: self.groups.to_vec(),
                given,
            };
            let frame_start = std::time::Instant::now();
            let before = g.new_agents();
            let mut next = g.next_frame(history, &fc)?;
            if let Some(h) = hold.as_deref_mut() {
                let after = g.new_agents();
                first_draws.0 += after.0 - before.0;
                first_draws.1 += after.1 - before.1;
                let held = h.hold(&next)?;
                let mut second = fc.clone();
                second.action = Some(held.action);
                second.given.push(held.map);
                next = g.next_frame(history, &second)?;
            }
            if let Some(rule) = self.road {
                let placed: Vec<usize> = fc.tokens.iter().map(|&(p, _)| p).collect();
                road += rule.apply(&mut next, history, &placed)?;
            }
            for (h, f) in history.iter_mut().zip(next) {
                h.push(f);
            }
            bar.inc(1);
            // Without a terminal the bar is hidden; a line per frame tells a log reader how far it got.
            if bar.is_hidden() {
                tracing::info!(
                    "frame {}/{}: {:.2} s",
                    k + 1,
                    a.frames,
                    frame_start.elapsed().as_secs_f64()
                );
            }
        }
        bar.finish_and_clear();
        Ok((road, first_draws))
    }
}
