//! Tracked objects moved one frame ahead (`backbone.track`): the agents' counterpart of AMA.
//!
//! Agents are coded in each frame's ego coordinates, in bins of absolute value. Where an agent will be
//! next is, to a few centimetres on most data, where its velocity takes it, seen from where the ego will
//! be: `p' = R(−dθ)·(p + v·Δt − d)`, `v' = R(−dθ)·v`, `θ' = θ − dθ` for the ego action `(dx, dy, dθ)`
//! of the next frame. Through token embeddings alone the model would have to learn that arithmetic on
//! bin indices (and did not, docs/decisions/002-agent-slot-hints.md). The TAR instead receives, at each slot, the embedding of
//! the slot so moved (re-binned; other tokens, empty slots and categories as they are) next to the
//! slot's own, and again at its output, so that "keep going" is a copy and what the model learns is the
//! departure from it. With `accel` the slot moves by constant acceleration instead: the velocity's change
//! since the window's previous frame is kept for one more frame. With `follow` a slot closing on a slower
//! one ahead in its lane brakes as much as it must to match its speed in time ([`FollowSpec`]).

use crate::config::Precision;
use crate::embed::FrameEmbedding;
use crate::spec::{BackboneSpec, FollowSpec, StopSpec, TrackSpec};
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, Int, Tensor};
use std::f64::consts::PI;
use umgen_ops::Kernels;
use umgen_ops::linear::linear;

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

    /// The input and output projections.
    pub(crate) fn linears(&self) -> (&Linear<B>, &Linear<B>) {
        (&self.input, &self.output)
    }

    /// What the TAR's input gets.
    pub fn input(&self, moved: Tensor<B, 3>, p: Precision, k: &Kernels) -> Tensor<B, 3> {
        linear(&self.input, moved, p, k)
    }

    /// What the TAR's output gets.
    pub fn output(&self, moved: Tensor<B, 3>, p: Precision, k: &Kernels) -> Tensor<B, 3> {
        linear(&self.output, moved, p, k)
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
    kernels: &Kernels,
) -> Option<(usize, Tensor<B, 3>)> {
    let k = spec.track.as_ref()?;
    let s = spec.segments.get(k.segment)?;
    let [b, t, _] = tokens.dims();
    let stops = k
        .stops
        .as_ref()
        .and_then(|st| spec.segments.get(st.segment))
        .map(|p| tokens.clone().narrow(2, p.offset, p.tokens));
    let ids = moved(tokens.narrow(2, s.offset, s.tokens), stops, action, k);
    embed
        .block_with(s.offset, ids.reshape([b * t, s.tokens]), kernels)
        .map(|e| (s.offset, e))
}

/// Ids `[b, t, slots · slot]` of the tracked segment with every slot whose x is a value moved by its
/// velocity over `spec.step_s` and into the frame reached by `action` `[b, t, 3]` = (dx, dy, dθ) of the
/// next frame. A slot moved past the x or y range becomes empty (`spec.pad` in every token) where the spec
/// has a pad: the data leaves such agents out, so a hint at the edge bin would tell the model to keep an
/// agent there for good. Other values past a field's range land in its end bins (a hint, not a token to
/// decode). `stops` `[b, t, m · slot]` are the ids of `spec.stops`'s segment, which the follow rule
/// brakes for (ignored without `spec.stops`).
pub fn moved<B: Backend>(
    ids: Tensor<B, 3, Int>,
    stops: Option<Tensor<B, 3, Int>>,
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
    let x_index = spec.fields[0].0;
    let occupied = column(x_index).lower_elem(spec.values as i64);
    let (dvx, dvy) = match &spec.follow {
        Some(f) => {
            let state = [x.clone(), y.clone(), vx.clone(), vy.clone(), heading.clone()];
            let points = spec
                .stops
                .as_ref()
                .zip(stops)
                .map(|(st, ids)| stop_points(ids, st));
            follow(f, spec.step_s, occupied.clone(), state, points, (dvx, dvy))
        }
        None => (dvx, dvy),
    };
    // Where the velocity takes the object, relative to where the ego will be, then turned by −dθ.
    let ds = spec.step_s;
    let px = x + (vx.clone() + dvx.clone().mul_scalar(0.5)).mul_scalar(ds) - dx;
    let py = y + (vy.clone() + dvy.clone().mul_scalar(0.5)).mul_scalar(ds) - dy;
    let turn = |a, b| by_minus(&cos, &sin, a, b);
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
    slots
        .mask_where(occupied.expand([b, t, s, k]), moved)
        .reshape([b, t, l])
}

/// The velocity changes `(dvx, dvy)` `[b, t, s, 1]` of slots `[b, t, s, 1]` (`occupied`, and their x, y,
/// vx, vy and heading) with the braking [`FollowSpec`] asks for over a step of `dt` seconds where it is
/// harder than the change along the slot's heading. The arithmetic is [`crate::track`]'s hint, op for op
/// in f32, which the generation engine repeats (its host and device `track` ops).
fn follow<B: Backend>(
    f: &FollowSpec,
    dt: f64,
    occupied: Tensor<B, 4, Bool>,
    [x, y, vx, vy, heading]: [Tensor<B, 4>; 5],
    stops: Option<(Leaders<B>, f64)>,
    (dvx, dvy): (Tensor<B, 4>, Tensor<B, 4>),
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let (c, s) = (heading.clone().cos(), heading.sin());
    let speed = vx.clone() * c.clone() + vy.clone() * s.clone();
    let me = [x.clone(), y.clone(), c.clone(), s.clone(), speed.clone()];
    // The other slots as leaders along dim 3.
    let other = |v: &Tensor<B, 4>| v.clone().swap_dims(2, 3);
    let slots = Leaders {
        at: [other(&x), other(&y)],
        way: [other(&c), other(&s)],
        velocity: Some([other(&vx), other(&vy)]),
        present: occupied.clone().swap_dims(2, 3),
    };
    let mut hardest = hardest_need(f, &me, slots, f.min_gap_m);
    if let Some((points, gap)) = stops {
        hardest = hardest.max_pair(hardest_need(f, &me, points, gap));
    }
    let brakes = occupied.bool_and(hardest.clone().greater_equal_elem(f.onset_m_s2));
    let target = hardest
        .clamp_max(f.max_m_s2)
        .mul_scalar(-dt)
        .max_pair(speed.neg());
    let change = dvx.clone() * c.clone() + dvy.clone() * s.clone();
    let delta = (target - change).clamp_max(0.0).mask_fill(brakes.bool_not(), 0.0);
    (dvx + delta.clone() * c, dvy + delta * s)
}

/// Objects a slot may brake for, along dim 3 of `[b, t, 1, j]` tensors: their centres, the cosine and
/// sine of their headings, their velocities (`None`: standing) and whether each is there.
struct Leaders<B: Backend> {
    at: [Tensor<B, 4>; 2],
    way: [Tensor<B, 4>; 2],
    velocity: Option<[Tensor<B, 4>; 2]>,
    present: Tensor<B, 4, Bool>,
}

/// The hardest braking `[b, t, s, 1]` that each slot `me` (x, y, cos and sin of the heading, speed
/// along it; `[b, t, s, 1]`) needs for `leaders` to keep `gap` metres between centres, 0 where none
/// leads it.
fn hardest_need<B: Backend>(
    f: &FollowSpec,
    [x, y, c, s, speed]: &[Tensor<B, 4>; 5],
    leaders: Leaders<B>,
    gap: f64,
) -> Tensor<B, 4> {
    let [lx, ly] = leaders.at;
    let (dx, dy) = (lx - x.clone(), ly - y.clone());
    let along = dx.clone() * c.clone() + dy.clone() * s.clone();
    let across = dy * c.clone() - dx * s.clone();
    let [lc, ls] = leaders.way;
    let same_way = lc * c.clone() + ls * s.clone();
    let closing = match leaders.velocity {
        Some([lvx, lvy]) => speed.clone() - (lvx * c.clone() + lvy * s.clone()),
        None => speed.clone().expand(along.dims()),
    };
    let room = along.clone().sub_scalar(gap).clamp_min(f.min_room_m);
    let need = closing.clone() * closing.clone() / room.mul_scalar(2.0);
    let leads = leaders
        .present
        .expand(along.dims())
        .bool_and(along.greater_elem(0.0))
        .bool_and(across.abs().lower_equal_elem(f.half_width_m))
        .bool_and(same_way.greater_equal_elem(f.cos_heading))
        .bool_and(closing.greater_elem(0.0));
    need.mask_fill(leads.bool_not(), 0.0).max_dim(3)
}

/// The stop points of stop-segment ids `[b, t, m · slot]` as standing leaders `[b, t, 1, m]`, with the
/// gap a follower keeps: a slot holding a point in a stop state, with no slot at the same x and y ids
/// in a go state.
fn stop_points<B: Backend>(ids: Tensor<B, 3, Int>, st: &StopSpec) -> (Leaders<B>, f64) {
    let [b, t, l] = ids.dims();
    let m = l / st.slot;
    let slots = ids.reshape([b, t, m, st.slot]);
    let column = |i: usize| slots.clone().narrow(3, i, 1).swap_dims(2, 3);
    let [x, y, heading] = st.fields.map(|(i, bins)| centre(column(i), bins));
    let state = column(st.state);
    let any_of = |ids: &[u32]| {
        ids.iter().fold(state.clone().zeros_like().bool(), |acc, &id| {
            acc.bool_or(state.clone().equal_elem(i64::from(id)))
        })
    };
    let (stop, go) = (any_of(&st.stop), any_of(&st.go));
    // Point j (dim 3) is released by a go slot g (dim 2) at its x and y ids.
    let (xi, yi) = (column(st.fields[0].0), column(st.fields[1].0));
    let same = |v: &Tensor<B, 4, Int>| {
        let square = [b, t, m, m];
        v.clone()
            .expand(square)
            .equal(v.clone().swap_dims(2, 3).expand(square))
    };
    let released = same(&xi)
        .bool_and(same(&yi))
        .bool_and(go.swap_dims(2, 3).expand([b, t, m, m]))
        .any_dim(2);
    let present = xi
        .lower_elem(i64::from(st.values))
        .bool_and(stop)
        .bool_and(released.bool_not());
    let leaders = Leaders {
        at: [x, y],
        way: [heading.clone().cos(), heading.sin()],
        velocity: None,
        present,
    };
    (leaders, st.gap_m)
}

/// `(a, b)` turned by −θ, given `cos θ` and `sin θ` (broadcast): a vector seen from a frame turned by θ.
fn by_minus<B: Backend>(
    cos: &Tensor<B, 4>,
    sin: &Tensor<B, 4>,
    a: Tensor<B, 4>,
    b: Tensor<B, 4>,
) -> (Tensor<B, 4>, Tensor<B, 4>) {
    (
        cos.clone() * a.clone() + sin.clone() * b.clone(),
        cos.clone() * b - sin.clone() * a,
    )
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
    let (ux, uy) = by_minus(&turn.clone().cos(), &turn.sin(), pvx, pvy);
    let (dvx, dvy) = (vx.clone() - ux, vy.clone() - uy);
    let was_there = column(spec.fields[0].0).lower_elem(spec.values as i64);
    let ahead = ((vx.clone() + dvx.clone()) * vx + (vy.clone() + dvy.clone()) * vy).greater_equal_elem(0.0);
    let drop = was_there.bool_and(ahead).bool_not();
    (dvx.mask_fill(drop.clone(), 0.0), dvy.mask_fill(drop, 0.0))
}

#[cfg(test)]
mod tests;

#[cfg(test)]
mod stop_tests;
