//! Tracked objects moved one frame ahead (`backbone.track`): the agents' counterpart of AMA.
//!
//! Agents are coded in each frame's ego coordinates, in bins of absolute value. Where an agent will be
//! next is, to a few centimetres on most data, where its velocity takes it, seen from where the ego will
//! be: `p' = R(−dθ)·(p + v·Δt − d)`, `v' = R(−dθ)·v`, `θ' = θ − dθ` for the ego action `(dx, dy, dθ)`
//! of the next frame. Through token embeddings alone the model would have to learn that arithmetic on
//! bin indices (and did not, docs/results.md). The TAR instead receives, at each slot, the embedding of
//! the slot so moved (re-binned; other tokens, empty slots and categories as they are) next to the
//! slot's own, and again at its output, so that "keep going" is a copy and what the model learns is the
//! departure from it.

use crate::config::Precision;
use crate::embed::FrameEmbedding;
use crate::precision::linear;
use crate::spec::{BackboneSpec, TrackSpec};
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};
use std::f64::consts::PI;

/// The two projections of the moved slots' embeddings: one added to the TAR's input at each slot, one
/// to its output (what the heads and the OAR read), which starts at zero so that a fresh model begins as
/// one without it.
#[derive(Module, Debug)]
pub struct TrackProjection<B: Backend> {
    input: Linear<B>,
    output: Linear<B>,
}

impl<B: Backend> TrackProjection<B> {
    /// Projections of width `d`.
    pub fn new(d: usize, dev: &B::Device) -> Self {
        Self {
            input: LinearConfig::new(d, d).init(dev),
            output: LinearConfig::new(d, d)
                .with_initializer(Initializer::Zeros)
                .init(dev),
        }
    }

    /// What the TAR's input gets.
    pub fn input(&self, moved: Tensor<B, 3>, p: Precision) -> Tensor<B, 3> {
        linear(&self.input, moved, p)
    }

    /// What the TAR's output gets.
    pub fn output(&self, moved: Tensor<B, 3>, p: Precision) -> Tensor<B, 3> {
        linear(&self.output, moved, p)
    }
}

/// The tracked slots of frames `tokens` `[b, t, N]` moved by the next actions `action` `[b, t, 3]`
/// ([`moved`]) and embedded like a frame's: their content offset and embeddings `[b·t, L, d]`; `None`
/// when the spec tracks nothing.
pub(crate) fn embed_moved<B: Backend>(
    spec: &BackboneSpec,
    embed: &FrameEmbedding<B>,
    tokens: Tensor<B, 3, Int>,
    action: Tensor<B, 3>,
) -> Option<(usize, Tensor<B, 3>)> {
    let k = spec.track.as_ref()?;
    let s = spec.segments.get(k.segment)?;
    let [b, t, _] = tokens.dims();
    let ids = moved(tokens.narrow(2, s.offset, s.tokens), action, k);
    embed
        .forward_block(s.offset, ids.reshape([b * t, s.tokens]))
        .map(|e| (s.offset, e))
}

/// Ids `[b, t, slots · slot]` of the tracked segment with every slot whose x is a value moved by its
/// velocity over `spec.step_s` and into the frame reached by `action` `[b, t, 3]` = (dx, dy, dθ) of the
/// next frame. A slot moved past the x or y range becomes empty (`spec.pad` in every token) where the spec
/// has a pad: the data leaves such agents out, so a hint at the edge bin would tell the model to keep an
/// agent there for good. Other values past a field's range land in its end bins (a hint, not a token to
/// decode).
pub fn moved<B: Backend>(
    ids: Tensor<B, 3, Int>,
    action: Tensor<B, 3>,
    spec: &TrackSpec,
) -> Tensor<B, 3, Int> {
    let [b, t, l] = ids.dims();
    let (k, s) = (spec.slot, l / spec.slot);
    let slots = ids.reshape([b, t, s, k]);
    let column = |i: usize| slots.clone().narrow(3, i, 1);
    let [x, y, vx, vy, heading] = spec.fields.map(|(i, (lo, hi, n))| {
        let width = (hi - lo) / f64::from(n);
        column(i).float().add_scalar(0.5).mul_scalar(width).add_scalar(lo)
    });
    let act = |c: usize| action.clone().narrow(2, c, 1).reshape([b, t, 1, 1]);
    let (dx, dy, dtheta) = (act(0), act(1), act(2));
    let (cos, sin) = (dtheta.clone().cos(), dtheta.clone().sin());
    // Where the velocity takes the object, relative to where the ego will be, then turned by −dθ.
    let px = x + vx.clone().mul_scalar(spec.step_s) - dx;
    let py = y + vy.clone().mul_scalar(spec.step_s) - dy;
    let turn = |a: Tensor<B, 4>, b: Tensor<B, 4>| {
        (
            cos.clone() * a.clone() + sin.clone() * b.clone(),
            cos.clone() * b - sin.clone() * a,
        )
    };
    let (nx, ny) = turn(px, py);
    let within = |v: &Tensor<B, 4>, (_, (lo, hi, _)): (usize, (f64, f64, u32))| {
        v.clone()
            .greater_equal_elem(lo)
            .bool_and(v.clone().lower_elem(hi))
    };
    let stays = within(&nx, spec.fields[0]).bool_and(within(&ny, spec.fields[1]));
    let (nvx, nvy) = turn(vx, vy);
    let h = heading - dtheta;
    let h = h.clone() - h.add_scalar(PI).div_scalar(2.0 * PI).floor().mul_scalar(2.0 * PI);
    let new = [nx, ny, nvx, nvy, h];
    let mut columns: Vec<Tensor<B, 4, Int>> = (0..k).map(column).collect();
    for ((i, (lo, hi, n)), v) in spec.fields.iter().zip(new) {
        let width = (hi - lo) / f64::from(*n);
        columns[*i] = v
            .sub_scalar(*lo)
            .div_scalar(width)
            .floor()
            .clamp(0.0, f64::from(*n - 1))
            .int();
    }
    let mut moved = Tensor::cat(columns, 3);
    if let Some(pad) = spec.pad {
        moved = moved.mask_fill(stays.bool_not().expand([b, t, s, k]), i64::from(pad));
    }
    let x_index = spec.fields[0].0;
    let occupied = column(x_index)
        .lower_elem(spec.values as i64)
        .expand([b, t, s, k]);
    slots.mask_where(occupied, moved).reshape([b, t, l])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    type F = burn::backend::Flex;

    fn spec() -> TrackSpec {
        TrackSpec {
            segment: 0,
            slot: 6,
            values: 8,
            fields: [
                (0, (-4.0, 4.0, 8)),
                (1, (-4.0, 4.0, 8)),
                (2, (-2.0, 2.0, 8)),
                (3, (-2.0, 2.0, 8)),
                (4, (-PI, PI, 8)),
            ],
            step_s: 0.5,
            pad: Some(9),
        }
    }

    /// The moved slot on the host: the object's place after `step_s` in the plane of the current frame,
    /// then seen from the next ego pose `(dx, dy, dθ)` as complex numbers (`(p − d)·e^{−iθ}`).
    fn host(slot: &[i64], act: [f64; 3], k: &TrackSpec) -> (Vec<i64>, bool) {
        if slot[0] >= i64::from(k.values) {
            return (slot.to_vec(), false);
        }
        let value = |j: usize| {
            let (i, (lo, hi, n)) = k.fields[j];
            lo + (slot[i] as f64 + 0.5) * (hi - lo) / f64::from(n)
        };
        let (p, v) = ((value(0), value(1)), (value(2), value(3)));
        let (c, s) = (act[2].cos(), -act[2].sin());
        let mul = |(a, b): (f64, f64)| (a * c - b * s, a * s + b * c);
        let q = mul((p.0 + v.0 * k.step_s - act[0], p.1 + v.1 * k.step_s - act[1]));
        let w = mul(v);
        let h = (value(4) - act[2] + PI).rem_euclid(2.0 * PI) - PI;
        let mut out = slot.to_vec();
        let mut near_edge = false;
        for ((i, (lo, hi, n)), x) in k.fields.iter().zip([q.0, q.1, w.0, w.1, h]) {
            let f = (x - lo) / ((hi - lo) / f64::from(*n));
            near_edge |= (f - f.round()).abs() < 1e-4;
            out[*i] = (f.floor() as i64).clamp(0, i64::from(*n) - 1);
        }
        let inside = |x: f64, j: usize| (k.fields[j].1.0..k.fields[j].1.1).contains(&x);
        if let (Some(pad), false) = (k.pad, inside(q.0, 0) && inside(q.1, 1)) {
            out = vec![i64::from(pad); slot.len()];
        }
        (out, near_edge)
    }

    #[test]
    fn slots_move_as_a_host_computation_says() {
        let k = spec();
        let (b, t, s) = (2, 3, 5);
        let mut seed = 7u64;
        let mut draw = |n: u64| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) % n) as i64
        };
        // Values 0..8, category 8 in the last token; slot 2 of each frame empty (pad 9).
        let ids: Vec<i64> = (0..b * t * s)
            .flat_map(|i| {
                let empty = i % s == 2;
                (0..k.slot)
                    .map(|j| match (empty, j) {
                        (true, _) => 9,
                        (false, 5) => 8,
                        _ => draw(8),
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        let acts: Vec<f64> = (0..b * t)
            .flat_map(|i| {
                [
                    0.9 + 0.37 * i as f64,
                    -0.21 + 0.05 * i as f64,
                    0.13 - 0.2 * i as f64,
                ]
            })
            .collect();
        let dev = Default::default();
        let got = moved::<F>(
            Tensor::from_data(TensorData::new(ids.clone(), [b, t, s * k.slot]), &dev),
            Tensor::from_data(
                TensorData::new(acts.iter().map(|&a| a as f32).collect::<Vec<_>>(), [b, t, 3]),
                &dev,
            ),
            &k,
        );
        let got: Vec<i64> = got.into_data().iter::<i64>().collect();
        let (mut moved_slots, mut changed, mut left) = (0, 0, 0);
        for (f, act) in acts.chunks(3).enumerate() {
            for slot in 0..s {
                let at = (f * s + slot) * k.slot;
                let (want, near_edge) = host(&ids[at..at + k.slot], [act[0], act[1], act[2]], &k);
                let have = &got[at..at + k.slot];
                if !near_edge {
                    assert_eq!(have, want.as_slice(), "frame {f} slot {slot}");
                }
                if have.iter().all(|&id| id == 9) {
                    left += usize::from(slot != 2);
                } else {
                    assert_eq!(have[5], ids[at + 5], "the category stays");
                }
                moved_slots += usize::from(slot != 2);
                changed += usize::from(have != &ids[at..at + k.slot]);
            }
        }
        assert_eq!(moved_slots, 24);
        assert!(changed >= 20, "{changed} of 24 slots moved");
        // Both cases occur: slots that leave the ±4 m window (empty) and slots that stay.
        assert!((3..=21).contains(&left), "{left} of 24 slots left");
    }

    #[test]
    fn a_standing_ego_and_object_stay_in_their_bins() {
        // No ego motion, no velocity (bins 3 and 4 of ±2 m/s straddle 0: centre ±0.25 m/s moves 0.125 m,
        // inside the 1 m bin from its centre), heading kept: the same ids.
        let k = spec();
        let slot = [2i64, 5, 4, 3, 6, 8];
        let dev = Default::default();
        let got = moved::<F>(
            Tensor::from_data(TensorData::new(slot.to_vec(), [1, 1, 6]), &dev),
            Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
            &k,
        );
        assert_eq!(got.into_data().iter::<i64>().collect::<Vec<_>>(), slot.to_vec());
    }

    #[test]
    fn a_slot_moved_out_of_the_window_empties_where_there_is_a_pad() {
        // x at bin 7 (3.5 m) with vx at bin 7 (1.75 m/s): 0.875 m further is past the +4 m edge.
        let slot = [7i64, 5, 7, 4, 6, 8];
        let dev = Default::default();
        let run = |k: &TrackSpec| {
            moved::<F>(
                Tensor::from_data(TensorData::new(slot.to_vec(), [1, 1, 6]), &dev),
                Tensor::from_data(TensorData::new(vec![0.0f32; 3], [1, 1, 3]), &dev),
                k,
            )
            .into_data()
            .iter::<i64>()
            .collect::<Vec<_>>()
        };
        assert_eq!(
            run(&spec()),
            vec![9; 6],
            "the data drops agents that leave the window"
        );
        let clamped = run(&TrackSpec { pad: None, ..spec() });
        assert_eq!(clamped, vec![7, 5, 7, 4, 6, 8], "without a pad: the end bin");
    }
}
