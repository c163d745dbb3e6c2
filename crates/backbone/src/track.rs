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
    let [x, y, vx, vy, heading] = spec.fields.map(|(i, bins)| centre(column(i), bins));
    let act = |c: usize| action.clone().narrow(2, c, 1).reshape([b, t, 1, 1]);
    let (dx, dy, dtheta) = (act(0), act(1), act(2));
    let (cos, sin) = (dtheta.clone().cos(), dtheta.clone().sin());
    // The velocity's change over the last frame, kept for one more (`spec.accel`).
    let (dvx, dvy) = if spec.accel && t > 1 {
        change(&slots, &action, spec, (vx.clone(), vy.clone()))
    } else {
        (vx.zeros_like(), vy.zeros_like())
    };
    // Where the velocity takes the object, relative to where the ego will be, then turned by −dθ.
    let ds = spec.step_s;
    let px = x + (vx.clone() + dvx.clone().mul_scalar(0.5)).mul_scalar(ds) - dx;
    let py = y + (vy.clone() + dvy.clone().mul_scalar(0.5)).mul_scalar(ds) - dy;
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
    let (nvx, nvy) = turn(vx + dvx, vy + dvy);
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

/// The centres `[b, t, s, 1]` of the bins `(lo, hi, n)` that ids `[b, t, s, 1]` name.
fn centre<B: Backend>(ids: Tensor<B, 4, Int>, (lo, hi, n): (f64, f64, u32)) -> Tensor<B, 4> {
    let width = (hi - lo) / f64::from(n);
    ids.float().add_scalar(0.5).mul_scalar(width).add_scalar(lo)
}

/// How much each slot's velocity `(vx, vy)` (frame t's coordinates) changed since frame t − 1 of the
/// window `slots` `[b, t, s, k]` (`t > 1`), whose velocity is first turned into frame t by the ego's turn
/// between them (the `action` of frame t − 1). Zero for the window's first frame, for a slot empty at
/// t − 1, and where keeping the change would turn the velocity around (a braking object stops; constant
/// acceleration would send it backwards).
fn change<B: Backend>(
    slots: &Tensor<B, 4, Int>,
    action: &Tensor<B, 3>,
    spec: &TrackSpec,
    (vx, vy): (Tensor<B, 4>, Tensor<B, 4>),
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let [b, t, _, _] = slots.dims();
    let before = Tensor::cat(
        vec![slots.clone().narrow(1, 0, 1), slots.clone().narrow(1, 0, t - 1)],
        1,
    );
    let column = |i: usize| before.clone().narrow(3, i, 1);
    let [_, _, (ivx, bvx), (ivy, bvy), _] = spec.fields;
    let (pvx, pvy) = (centre(column(ivx), bvx), centre(column(ivy), bvy));
    let dtheta = action.clone().narrow(2, 2, 1);
    let turn = Tensor::cat(
        vec![
            dtheta.clone().narrow(1, 0, 1).zeros_like(),
            dtheta.narrow(1, 0, t - 1),
        ],
        1,
    )
    .reshape([b, t, 1, 1]);
    let (cos, sin) = (turn.clone().cos(), turn.sin());
    let dvx = vx.clone() - (cos.clone() * pvx.clone() + sin.clone() * pvy.clone());
    let dvy = vy.clone() - (cos * pvy - sin * pvx);
    let was_there = column(spec.fields[0].0).lower_elem(spec.values as i64);
    let ahead = ((vx.clone() + dvx.clone()) * vx + (vy.clone() + dvy.clone()) * vy).greater_equal_elem(0.0);
    let drop = was_there.bool_and(ahead).bool_not();
    (dvx.mask_fill(drop.clone(), 0.0), dvy.mask_fill(drop, 0.0))
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
            accel: false,
        }
    }

    /// The moved slot on the host: the object's place after `step_s` in the plane of the current frame,
    /// then seen from the next ego pose `(dx, dy, dθ)` as complex numbers (`(p − d)·e^{−iθ}`).
    fn host(slot: &[i64], before: Option<(&[i64], f64)>, act: [f64; 3], k: &TrackSpec) -> (Vec<i64>, bool) {
        if slot[0] >= i64::from(k.values) {
            return (slot.to_vec(), false);
        }
        let value = |s: &[i64], j: usize| {
            let (i, (lo, hi, n)) = k.fields[j];
            lo + (s[i] as f64 + 0.5) * (hi - lo) / f64::from(n)
        };
        let value = |j: usize| value(slot, j);
        let (p, v) = ((value(0), value(1)), (value(2), value(3)));
        // e^{−iθ} as (cos, sin) of −θ, and complex multiplication by it.
        let turn = |theta: f64, (a, b): (f64, f64)| {
            let (c, s) = (theta.cos(), -theta.sin());
            (a * c - b * s, a * s + b * c)
        };
        // Constant acceleration: the change since the previous frame's velocity (turned into this frame);
        // none after an empty slot or where it would reverse the velocity.
        let dv = match before {
            Some((prev, theta)) if prev[0] < i64::from(k.values) => {
                let u = turn(theta, (value_of(prev, 2, k), value_of(prev, 3, k)));
                let d = (v.0 - u.0, v.1 - u.1);
                if (v.0 + d.0) * v.0 + (v.1 + d.1) * v.1 >= 0.0 {
                    d
                } else {
                    (0.0, 0.0)
                }
            }
            _ => (0.0, 0.0),
        };
        let step = (v.0 + 0.5 * dv.0, v.1 + 0.5 * dv.1);
        let q = turn(
            act[2],
            (p.0 + step.0 * k.step_s - act[0], p.1 + step.1 * k.step_s - act[1]),
        );
        let w = turn(act[2], (v.0 + dv.0, v.1 + dv.1));
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

    fn value_of(s: &[i64], j: usize, k: &TrackSpec) -> f64 {
        let (i, (lo, hi, n)) = k.fields[j];
        lo + (s[i] as f64 + 0.5) * (hi - lo) / f64::from(n)
    }

    #[test]
    fn slots_move_as_a_host_computation_says() {
        let (b, t, s) = (2, 3, 5);
        let mut seed = 7u64;
        let mut draw = |n: u64| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) % n) as i64
        };
        // Values 0..8, category 8 in the last token; slot 2 of each frame empty (pad 9), and a few
        // others, so that some slots are new in their frame.
        let empty = |i: usize| i % s == 2 || i % 7 == 3;
        let ids: Vec<i64> = (0..b * t * s)
            .flat_map(|i| {
                (0..6)
                    .map(|j| match (empty(i), j) {
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
        let occupied = (0..b * t * s).filter(|&i| !empty(i)).count();
        for accel in [false, true] {
            let k = TrackSpec { accel, ..spec() };
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
            let (mut changed, mut left) = (0, 0);
            for (f, act) in acts.chunks(3).enumerate() {
                for slot in 0..s {
                    let at = (f * s + slot) * k.slot;
                    // The same slot one frame earlier in the window, and the ego's turn between them.
                    let before = (accel && f % t > 0).then(|| {
                        let p = at - s * k.slot;
                        (&ids[p..p + k.slot], acts[3 * (f - 1) + 2])
                    });
                    let slot_ids = &ids[at..at + k.slot];
                    let (want, near_edge) = host(slot_ids, before, [act[0], act[1], act[2]], &k);
                    let have = &got[at..at + k.slot];
                    if !near_edge {
                        assert_eq!(have, want.as_slice(), "accel {accel}, frame {f}, slot {slot}");
                    }
                    if empty(f * s + slot) {
                        continue;
                    }
                    if have.iter().all(|&id| id == 9) {
                        left += 1;
                    } else {
                        assert_eq!(have[5], ids[at + 5], "the category stays");
                    }
                    changed += usize::from(have != slot_ids);
                }
            }
            assert!(changed + 4 >= occupied, "{changed} of {occupied} slots moved");
            // Both cases occur: slots that leave the ±4 m window (empty) and slots that stay.
            assert!(
                left >= 3 && left + 3 <= occupied,
                "{left} of {occupied} slots left"
            );
        }
    }

    #[test]
    fn constant_acceleration_keeps_the_change_and_stops_rather_than_reverses() {
        // Two frames of one slot (x 0.5 m, y 1.5 m, vy 0.25 m/s), no ego motion. vx 0.75 m/s after
        // −1.75: the change (2.5 m/s) kept puts x at 0.5 + 0.5 · (0.75 + 1.25) = 1.5 m (bin 5; 0.875 m, bin
        // 4, at constant velocity) and vx at 3.25 m/s (past the range: bin 7). Braking from 1.75 to 0.25
        // m/s would reverse it (−1.25): constant velocity instead.
        let dev = Default::default();
        let run = |vx: [i64; 2], accel: bool| {
            let ids = vec![4i64, 5, vx[0], 4, 4, 8, 4, 5, vx[1], 4, 4, 8];
            moved::<F>(
                Tensor::from_data(TensorData::new(ids, [1, 2, 6]), &dev),
                Tensor::from_data(TensorData::new(vec![0.0f32; 6], [1, 2, 3]), &dev),
                &TrackSpec { accel, ..spec() },
            )
            .into_data()
            .iter::<i64>()
            .collect::<Vec<_>>()
        };
        // The window's first frame has no past: constant velocity (x −0.375 m, bin 3).
        assert_eq!(run([0, 5], true), vec![3, 5, 0, 4, 4, 8, 5, 5, 7, 4, 4, 8]);
        assert_eq!(run([0, 5], false)[6..], [4, 5, 5, 4, 4, 8]);
        assert_eq!(run([7, 4], true)[6..], [4, 5, 4, 4, 4, 8]);
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
