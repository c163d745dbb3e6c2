//! `umgen generate --map-memory`: each scene's map held fixed in the world ([`MapMemory`]).
//!
//! A scene's memory starts with the maps its context frames' codes decode to, newest first, each at its
//! frame's ego pose. Each generated frame is then drawn twice. The first draw gives the ego action,
//! so the new pose, and a map. That map, decoded, fills the ground the memory has not seen, the
//! memory's cells cover the rest, and the map tokenizer encodes the result. The second draw places
//! those codes and the same action, so the agents and camera are drawn on the held map.
//! The ground the first draw added is remembered as drawn.

use super::contexts::ContextClip;
use super::frame_map::FrameMap;
use anyhow::Context;
use std::ops::Range;
use umgen::Bundle;
use umgen::generate::GivenSegment;
use umgen::modality::{Modality, ModalityRegistry};
use umgen::scene::{EgoPose, Frame, SceneClip};
use umgen_render::MapMemory;

/// What the memory did over a rollout, for the log and `meta.json`.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub(super) struct HeldCount {
    /// Generated frames held, over all scenes.
    pub frames: u64,
    /// Their map pixels, and those the memory covered.
    pub pixels: u64,
    pub held: u64,
    /// Their map codes, and those that differ from the first draw's.
    pub codes: u64,
    pub changed: u64,
}

/// One scene's memory and its ego pose in the newest frame.
struct Scene {
    memory: MapMemory,
    pose: EgoPose,
}

/// The memories of a rollout's scenes and what reads and writes their frames.
pub(super) struct MapHold<'a> {
    map: FrameMap<'a>,
    ego: &'a dyn Modality,
    /// The ego action's content positions.
    action: Range<usize>,
    interval: f64,
    scenes: Vec<Scene>,
    count: HeldCount,
}

/// One scene's first draw: its action tokens and the map codes to place in the second draw.
pub(super) struct Held {
    pub action: Vec<Vec<u32>>,
    pub map: GivenSegment,
}

impl<'a> MapHold<'a> {
    /// Memories for `scenes` scenes, scene `s` continuing `contexts[context_of(s)]` (whose token rows
    /// are `context_rows`), or from nothing; `action_segment` is the ego action's segment, `recorded`
    /// the segments given from the contexts.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        bundle: &Bundle,
        registry: &'a ModalityRegistry,
        action_segment: Option<usize>,
        recorded: &[usize],
        contexts: &[ContextClip],
        context_rows: &[Vec<Vec<u32>>],
        scenes: usize,
        context_of: impl Fn(usize) -> Option<usize>,
        interval: f64,
    ) -> anyhow::Result<Self> {
        let map = FrameMap::new(bundle, registry, "--map-memory", "holds the map")?;
        anyhow::ensure!(
            !recorded.contains(&map.segment),
            "--map-memory holds the map the model draws; with `{}` recorded it draws none",
            map.modality
        );
        let a = action_segment
            .context("--map-memory moves the map with the ego action, and this model has no ego action")?;
        let ego = registry
            .modalities()
            .get(a)
            .context("the ego action's segment has no modality")?;
        let view = map.view.clone();
        let mut hold = Self {
            map,
            ego: ego.as_ref(),
            action: registry.layout()?.segments()[a].content(),
            interval,
            scenes: Vec::with_capacity(scenes),
            count: HeldCount::default(),
        };
        for s in 0..scenes {
            let mut memory = MapMemory::new(view.clone())?;
            let mut pose = EgoPose::default();
            if let Some(c) = context_of(s) {
                let clip = &contexts[c].clip;
                for (t, frame) in clip.frames.iter().enumerate().rev() {
                    let raster = hold
                        .map
                        .decode(&context_rows[c][t])
                        .with_context(|| format!("context {} frame {t}", contexts[c].id))?;
                    memory.remember(&raster, &frame.ego.pose2())?;
                }
                pose = clip.frames.last().map(|f| f.ego).unwrap_or_default();
            }
            hold.scenes.push(Scene { memory, pose });
        }
        Ok(hold)
    }

    /// What the memories did so far.
    pub(super) fn count(&self) -> HeldCount {
        self.count
    }

    /// Moves each scene to the pose its first draw `first[s]` reaches, holds its map there, and
    /// remembers the ground the draw added; returns the actions and the map codes for the second draw.
    pub(super) fn hold(&mut self, first: &[Vec<u32>]) -> anyhow::Result<Held> {
        anyhow::ensure!(
            first.len() == self.scenes.len(),
            "{} frames drawn for {} scenes",
            first.len(),
            self.scenes.len()
        );
        let mut action = Vec::with_capacity(first.len());
        let mut frames = Vec::with_capacity(first.len());
        for (s, row) in first.iter().enumerate() {
            let ids = row
                .get(self.action.clone())
                .with_context(|| format!("scene {s}: the frame has no ego action at {:?}", self.action))?;
            let mut f = Frame::default();
            self.ego
                .detokenize(ids, &mut f)
                .with_context(|| format!("scene {s}: decoding the ego action"))?;
            let drawn = self.map.decode(row).with_context(|| format!("scene {s}"))?;
            let scene = &mut self.scenes[s];
            scene.pose = scene.pose.advance(&f.action, self.interval);
            let pose = scene.pose.pose2();
            let (map, held) = scene.memory.recall(&pose, &drawn)?;
            scene.memory.remember(&map, &pose)?;
            self.count.frames += 1;
            self.count.pixels += (map.height * map.width) as u64;
            self.count.held += held as u64;
            action.push(ids.to_vec());
            frames.push(Frame {
                time: s as f64 * self.interval,
                map: Some(map),
                ..Frame::default()
            });
        }
        let clip = SceneClip::new("held", self.interval, frames)?;
        let codes = self
            .map
            .map
            .tokenize_clip(&clip)
            .context("encoding the held maps")?;
        for (row, c) in first.iter().zip(&codes) {
            self.count.codes += c.len() as u64;
            self.count.changed += row[self.map.codes.clone()]
                .iter()
                .zip(c)
                .filter(|(a, b)| a != b)
                .count() as u64;
        }
        Ok(Held {
            action,
            map: GivenSegment {
                segment: self.map.segment,
                ids: codes,
            },
        })
    }
}
