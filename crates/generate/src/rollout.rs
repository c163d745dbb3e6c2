//! One new frame at a time: the ego action (predicted or forced), TAR over the last ≤ `window` frames,
//! then the OAR position by position over a key/value cache, each content token drawn with its
//! modality's sampling settings. Start and end tokens are placed, not drawn; a known ego action is
//! placed at its positions (the OAR still reads it, as in training).

use crate::device_draw::DeviceTopK;
use crate::error::{GenerateError, Result};
use crate::rules::{Allowed, FrameRules, Rules, allowed, check_frame};
pub use crate::rules::{FrameControl, GivenSegment, TokenGroups};
use crate::sampling::Sampling;
use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use rand::{SeedableRng, rngs::StdRng};
use umgen_backbone::{Backbone, Slot};

mod settings;
mod speculate;
mod uniforms;
mod window;

/// Uniform numbers uploaded at once for the device draws of a frame, by default (16 MiB of f32): a
/// frame of the paper's layout at top-k 16 needs 1,536 × 16 per scene, so up to 170 scenes take one
/// upload per frame.
pub const DEFAULT_UNIFORM_BLOCK: usize = 1 << 22;

/// Window frames per pass of the ego module and the TAR by default: 64 frames of the paper's layout are
/// about 144k tokens, four times a `small` training batch per GPU, without the backward pass.
pub const DEFAULT_PASS_FRAMES: usize = 64;

/// Generates frames with a backbone.
#[derive(Debug)]
pub struct Generator<'a, B: Backend> {
    model: &'a Backbone<B>,
    sampling: Vec<Sampling>,
    window: usize,
    rng: StdRng,
    /// The device draws' own generator (their numbers are drawn ahead, a block at a time).
    device_rng: StdRng,
    slots: Vec<Slot>,
    on_device: bool,
    pass_frames: usize,
    uniform_block: usize,
    top_k: DeviceTopK,
    speculate: usize,
    /// Speculative blocks run and the positions they decided, since the generator was made.
    speculated: (u64, u64),
    /// New agents the new-agent rule tested and dropped, since the generator was made.
    new_agents: (u64, u64),
}

impl<'a, B: Backend> Generator<'a, B> {
    /// A generator drawing segment `s`'s tokens with `sampling[s]`, conditioning on at most `window`
    /// frames, seeded with `seed` (same seed, same model, same history: same frames).
    pub fn new(model: &'a Backbone<B>, sampling: Vec<Sampling>, window: usize, seed: u64) -> Result<Self> {
        let segs = &model.spec().segments;
        if sampling.len() != segs.len() {
            return Err(GenerateError::Settings(format!(
                "{} sampling settings for {} modalities",
                sampling.len(),
                segs.len()
            )));
        }
        for (s, seg) in sampling.iter().zip(segs) {
            s.validate(&format!("sampling.{}", seg.label))?;
        }
        if window == 0 {
            return Err(GenerateError::Settings(
                "window = 0: need at least one frame".into(),
            ));
        }
        Ok(Self {
            model,
            sampling,
            window,
            rng: StdRng::seed_from_u64(seed),
            device_rng: StdRng::seed_from_u64(seed ^ 0x9e37_79b9_7f4a_7c15),
            slots: model.slots(),
            on_device: false,
            pass_frames: DEFAULT_PASS_FRAMES,
            uniform_block: DEFAULT_UNIFORM_BLOCK,
            top_k: DeviceTopK::default(),
            speculate: 0,
            speculated: (0, 0),
            new_agents: (0, 0),
        })
    }

    /// The next frame `[m][N]` of each of `m` scenes, from their histories `[m][t][N]` (all of one length
    /// `t`; `t = 0` makes an initial scene without TAR, as in the paper).
    pub fn next_frame(&mut self, history: &[Vec<Vec<u32>>], control: &FrameControl) -> Result<Vec<Vec<u32>>> {
        let spec = self.model.spec();
        let m = check_frame(spec, history, control)?;
        let dev = self.model.devices().into_iter().next().unwrap_or_default();
        let frame = FrameRules::new(spec, &self.slots, history, control)?;
        let (action, h) = self.window_pass(history, control.action.as_ref(), &dev);
        let rules = frame.view(&control.groups);
        self.decode(h, action.as_ref(), &rules, m, &dev)
    }

    /// Per position of a frame: a content position drawn from its logits alone (no forced action, no
    /// placed id, no rule), which may go to the device or into a speculative block.
    fn free_draws(&self, action: Option<&Vec<Vec<u32>>>, rules: &Rules<'_>) -> Vec<bool> {
        let spec = self.model.spec();
        self.slots
            .iter()
            .enumerate()
            .map(|(p, slot)| match *slot {
                Slot::Content(s, i) => {
                    let forced = matches!((&spec.action, action),
                        (Some(a), Some(act)) if a.segment == s && i < act[0].len());
                    !forced && !rules.set_by_caller(p) && rules.free(p)
                }
                _ => false,
            })
            .collect()
    }

    /// With speculation on, the block that starts at `p`: its length (at least 2, at most the setting) and
    /// segment, over free positions of one segment.
    fn speculative_run(&self, p: usize, free: &[bool]) -> Option<(usize, usize)> {
        let Slot::Content(s, _) = self.slots[p] else {
            return None;
        };
        let l = (p..free.len().min(p + self.speculate))
            .take_while(|&q| free[q] && matches!(self.slots[q], Slot::Content(t, _) if t == s))
            .count();
        (self.speculate >= 2 && l >= 2).then_some((l, s))
    }

    /// The OAR pass over the new frame.
    fn decode(
        &mut self,
        h: Tensor<B, 3>,
        action: Option<&Vec<Vec<u32>>>,
        rules: &Rules<'_>,
        m: usize,
        dev: &B::Device,
    ) -> Result<Vec<Vec<u32>>> {
        let spec = self.model.spec();
        let n = spec.n;
        let d = h.dims()[2];
        let mut out = vec![vec![0u32; n]; m];
        let free = self.free_draws(action, rules);
        let drawn_on_device: Vec<bool> = free.iter().map(|&f| f && self.on_device).collect();
        let sizes = (0..n)
            .filter(|&p| drawn_on_device[p])
            .filter_map(|p| match self.slots[p] {
                Slot::Content(s, _) => Some(m * self.sampling[s].draw_width(spec.segments[s].vocab)),
                _ => None,
            })
            .collect();
        let mut uniforms = uniforms::UniformBlocks::<B>::new(sizes, self.uniform_block);
        let mut cache = self.model.oar_cache();
        let ego = rules.groups.iter().find_map(|g| g.boxes.as_ref().map(|b| b.ego));
        let mut boxes = crate::boxes::FrameBoxes::new(m, ego.unwrap_or([0.0, 0.0]));
        // Positions without rules (map and image codes) are drawn on the device and read back once, at the
        // end of the frame: their ids feed the next step where they are, with no host synchronisation.
        let (mut pending, mut on_device) = (Vec::new(), None);
        let mut p = 0;
        while p < n {
            if let Some((l, s)) = self.speculative_run(p, &free) {
                let block = speculate::Block {
                    p,
                    l,
                    s,
                    prev: on_device.take(),
                    h: &h,
                };
                let decided = self.speculate_block(block, &mut out, &mut cache, dev)?;
                self.speculated = (self.speculated.0 + 1, self.speculated.1 + decided as u64);
                p += decided;
                continue;
            }
            let prev = (p > 0).then(|| on_device.take().unwrap_or_else(|| ids_at(&out, p - 1, dev)));
            let w = self
                .model
                .oar_input_at(p, prev, h.clone().narrow(1, p, 1).reshape([m, d]));
            let o = self.model.oar_step(w, &mut cache)?;
            match self.slots[p] {
                Slot::Start(s) => out.iter_mut().for_each(|r| r[p] = spec.segments[s].vocab as u32),
                Slot::End(s) => out
                    .iter_mut()
                    .for_each(|r| r[p] = spec.segments[s].vocab as u32 + 1),
                Slot::Content(s, i) => {
                    let forced = match (&spec.action, action) {
                        (Some(a), Some(act)) if a.segment == s && i < act[0].len() => Some(act),
                        _ => None,
                    };
                    if let Some(act) = forced {
                        for (r, a) in out.iter_mut().zip(act) {
                            r[p] = a[i];
                        }
                    } else if let Some(id) = rules.placed[p] {
                        out.iter_mut().for_each(|r| r[p] = id);
                    } else if let Some(ids) = &rules.given[p] {
                        out.iter_mut().zip(ids).for_each(|(r, &id)| r[p] = id);
                    } else if drawn_on_device[p] {
                        let logits = self.model.logits_at(s, o, false);
                        let width = self.sampling[s].draw_width(logits.dims()[1]);
                        let u = uniforms.take(m, width, &mut self.device_rng, dev);
                        let ids = self.sampling[s].draw_rows_with(logits, u, self.top_k);
                        on_device = Some(ids.clone());
                        pending.push((p, ids));
                    } else if let Some(ids) = known_ids(rules, p, &out) {
                        // Nothing to draw in any scene (the rest of an empty agent slot): no logits, and
                        // so no wait for the device.
                        for (r, id) in out.iter_mut().zip(ids) {
                            r[p] = id;
                        }
                    } else {
                        let rows = host_rows(self.model.logits_at(s, o, false));
                        let smp = self.sampling[s];
                        for (r, l) in out.iter_mut().zip(&rows) {
                            match allowed(rules, p, r, true) {
                                Allowed::Only(id) => r[p] = id,
                                Allowed::Ids(ok) => {
                                    r[p] = draw_allowed(&smp, rules, p, l, &ok, &mut self.rng);
                                }
                            }
                        }
                        if let Some((pad, scenes)) = &rules.keep[p] {
                            let redraw: Vec<usize> =
                                (0..m).filter(|&b| scenes[b] && out[b][p] == *pad).collect();
                            if !redraw.is_empty() {
                                let hp = h.clone().narrow(1, p, 1).reshape([m, d]);
                                let tar = host_rows(self.model.logits_at(s, hp, true));
                                for b in redraw {
                                    // The TAR, which sees the history, decides: it may say pad again
                                    // (the agent leaves). A slot already emptied by its first token
                                    // stays empty.
                                    let Allowed::Ids(ok) = allowed(rules, p, &out[b], false) else {
                                        continue;
                                    };
                                    out[b][p] = draw_allowed(&smp, rules, p, &tar[b], &ok, &mut self.rng);
                                }
                            }
                        }
                    }
                }
            }
            // A finished group: the new-agent rule (groups placed by the caller are never dropped).
            if let Some((start, j, gi)) = &rules.group[p]
                && let g = &rules.groups[*gi]
                && *j + 1 == g.size
                && let Some(spec) = &g.boxes
                && !(*start..=p).any(|q| rules.set_by_caller(q))
            {
                for (b, row) in out.iter_mut().enumerate() {
                    if row[*start] == g.pad {
                        continue;
                    }
                    let newborn = rules.newborn[b][p];
                    let verdict = boxes.admit(b, *start, &row[*start..=p], spec, newborn);
                    self.new_agents.0 += u64::from(newborn);
                    let emptied = verdict
                        .emptied
                        .iter()
                        .copied()
                        .chain(verdict.drop.then_some(*start));
                    for first in emptied {
                        self.new_agents.1 += 1;
                        row[first..first + g.size].iter_mut().for_each(|x| *x = g.pad);
                    }
                }
            }
            p += 1;
        }
        if !pending.is_empty() {
            let (positions, ids): (Vec<usize>, Vec<_>) = pending.into_iter().unzip();
            let drawn: Vec<i64> = Tensor::stack::<2>(ids, 1).into_data().iter::<i64>().collect();
            for (row, got) in out.iter_mut().zip(drawn.chunks(positions.len())) {
                for (&p, &id) in positions.iter().zip(got) {
                    row[p] = id as u32;
                }
            }
        }
        Ok(out)
    }
}

/// The ids of position `p` in every scene when the rules leave nothing to draw in any of them (and no
/// keep rule may redraw them from the TAR).
fn known_ids(rules: &Rules<'_>, p: usize, out: &[Vec<u32>]) -> Option<Vec<u32>> {
    if rules.keep[p].is_some() {
        return None;
    }
    out.iter()
        .map(|r| match allowed(rules, p, r, true) {
            Allowed::Only(id) => Some(id),
            Allowed::Ids(_) => None,
        })
        .collect()
}

/// The ids of position `p` of every scene, on the device (the input of the next decoding step).
pub(crate) fn ids_at<B: Backend>(out: &[Vec<u32>], p: usize, dev: &B::Device) -> Tensor<B, 1, Int> {
    let ids: Vec<i64> = out.iter().map(|r| i64::from(r[p])).collect();
    Tensor::from_data(TensorData::new(ids, [out.len()]), dev)
}

/// Rows of a `[r, v]` tensor on the host.
pub(crate) fn host_rows<B: Backend>(t: Tensor<B, 2>) -> Vec<Vec<f32>> {
    let [_, v] = t.dims();
    let flat: Vec<f32> = t.into_data().iter::<f32>().collect();
    flat.chunks(v.max(1)).map(<[f32]>::to_vec).collect()
}

/// Draws position `p` from `logits` among the ids `ok` allows; at a token group's first position pad keeps
/// its untruncated share ([`Sampling::distribution_present`]).
fn draw_allowed(
    smp: &Sampling,
    rules: &Rules<'_>,
    p: usize,
    logits: &[f32],
    ok: &dyn Fn(u32) -> bool,
    rng: &mut StdRng,
) -> u32 {
    let l: Vec<f32> = logits
        .iter()
        .enumerate()
        .map(|(id, &x)| if ok(id as u32) { x } else { f32::NEG_INFINITY })
        .collect();
    let group_first = match rules.group[p] {
        Some((_, 0, gi)) => rules.groups.get(gi),
        _ => None,
    };
    match group_first {
        Some(g) => smp.draw_present(&l, g.pad, rng),
        None => smp.draw(&l, rng),
    }
}
