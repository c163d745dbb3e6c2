//! The host's loops for the TAR input's parts (`rows.cu`'s `umgen_shift_block`, `umgen_align`,
//! `umgen_track`), with burn's arithmetic in its order (f32 operations one at a time; AMA's bilinear
//! weights in f64, as burn's CPU `grid_sample_2d`).

use super::host::HostExec;
use umgen_cuda::ops::{Align, ExecError, Op, Shift, Track, TrackFollow};

pub(super) fn run(x: &mut HostExec, op: &Op) -> Result<(), ExecError> {
    match op {
        Op::Shift(s) => shift(x, s),
        Op::Align(a) => align(x, a),
        Op::Track(t) => track(x, t),
        _ => Err(ExecError::Invalid(format!(
            "{} is not a frame operation",
            op.name()
        ))),
    }
}

fn shift(x: &mut HostExec, s: &Shift) -> Result<(), ExecError> {
    let fresh = x.f32s(s.fresh)[..s.m * s.len * s.d].to_vec();
    let v = x.f32s_mut(s.x);
    let frame = s.n * s.d;
    for scene in 0..s.m {
        for i in 0..s.len {
            let base = (scene * s.w * s.n + s.start + i) * s.d;
            for t in 0..s.w {
                for c in 0..s.d {
                    v[base + t * frame + c] = if t + 1 < s.w {
                        v[base + (t + 1) * frame + c]
                    } else {
                        fresh[(scene * s.len + i) * s.d + c]
                    };
                }
            }
        }
    }
    Ok(())
}

fn align(x: &mut HostExec, a: &Align) -> Result<(), ExecError> {
    let cells = a.rows * a.cols;
    let src = x.f32s(a.src)[..a.frames * cells * a.d].to_vec();
    let act = x.f32s(a.act)[..a.frames * 3].to_vec();
    let base = x.f32s(a.base)[..cells * 2].to_vec();
    let out = x.f32s_mut(a.x);
    for f in 0..a.frames {
        let (dx, dy, th) = (act[3 * f], act[3 * f + 1], act[3 * f + 2]);
        let (co, si) = (th.cos(), th.sin());
        let (tx, ty) = (dy * a.tx_scale, dx * a.ty_scale);
        for cell in 0..cells {
            let (gx, gy) = (base[2 * cell], base[2 * cell + 1]);
            let sx = co * gx + si * gy + tx;
            let sy = -si * gx + co * gy + ty;
            let px = (f64::from(sx) + 1.0) * a.cols as f64 / 2.0 - 0.5;
            let py = (f64::from(sy) + 1.0) * a.rows as f64 / 2.0 - 0.5;
            let (fx, fy) = (px.floor(), py.floor());
            let (x0, y0) = (fx as i64, fy as i64);
            let (ax, ay) = (px - fx, py - fy);
            let corners = [
                (x0, y0, (1.0 - ax) * (1.0 - ay)),
                (x0, y0 + 1, (1.0 - ax) * ay),
                (x0 + 1, y0, ax * (1.0 - ay)),
                (x0 + 1, y0 + 1, ax * ay),
            ];
            let o = (f * a.n + a.offset + cell) * a.d;
            for c in 0..a.d {
                let mut v = 0.0f64;
                for (cx, cy, wt) in corners {
                    let inside = cx >= 0 && cx < a.cols as i64 && cy >= 0 && cy < a.rows as i64;
                    let s = if inside {
                        f64::from(src[((f * cells) + cy as usize * a.cols + cx as usize) * a.d + c])
                    } else {
                        0.0
                    };
                    v += s * wt;
                }
                out[o + c] += v as f32;
            }
        }
    }
    Ok(())
}

fn track(x: &mut HostExec, t: &Track) -> Result<(), ExecError> {
    let tok = x.i32s(t.tok)[..t.frames * t.n].to_vec();
    let act = x.f32s(t.act)[..t.frames * 3].to_vec();
    let fl = &t.fields;
    let centre = |q: usize, id: i32| fl[q].centre(id);
    let mut out = vec![0i32; t.frames * t.slots * t.k];
    for f in 0..t.frames {
        let tf = f % t.w;
        let slot_ids = |slot: usize| {
            let at = f * t.n + t.offset + slot * t.k;
            (at, &tok[at..at + t.k])
        };
        // Every slot's values and velocity change first: the follow rule reads the other slots.
        let mut state = Vec::with_capacity(t.slots);
        for slot in 0..t.slots {
            let (at, ids) = slot_ids(slot);
            let v: [f32; 5] = std::array::from_fn(|q| centre(q, ids[fl[q].index]));
            let (mut dvx, mut dvy) = (0.0f32, 0.0f32);
            if t.accel && t.w > 1 {
                let before = if tf > 0 {
                    &tok[at - t.n..at - t.n + t.k]
                } else {
                    ids
                };
                let turn = if tf > 0 { act[3 * (f - 1) + 2] } else { 0.0 };
                let (pvx, pvy) = (centre(2, before[fl[2].index]), centre(3, before[fl[3].index]));
                let (tc, ts) = (turn.cos(), turn.sin());
                let ux = tc * pvx + ts * pvy;
                let uy = tc * pvy - ts * pvx;
                dvx = v[2] - ux;
                dvy = v[3] - uy;
                let was_there = before[fl[0].index] < t.values as i32;
                let ahead = (v[2] + dvx) * v[2] + (v[3] + dvy) * v[3];
                if !(was_there && ahead >= 0.0) {
                    (dvx, dvy) = (0.0, 0.0);
                }
            }
            state.push(SlotState {
                occupied: ids[fl[0].index] < t.values as i32,
                v,
                dv: [dvx, dvy],
            });
        }
        // The stop points braked for, as standing leaders (x, y, heading).
        let points = match (&t.stops, &t.follow) {
            (Some(st), Some(_)) => st.points(&tok, t.n, f),
            _ => Vec::new(),
        };
        let gap = t.stops.map_or(0.0, |st| st.gap);
        for slot in 0..t.slots {
            let (_, ids) = slot_ids(slot);
            let o = &mut out[(f * t.slots + slot) * t.k..(f * t.slots + slot + 1) * t.k];
            o.copy_from_slice(ids);
            let SlotState { occupied, v, dv } = state[slot];
            if !occupied {
                continue;
            }
            let [dvx, dvy] = match &t.follow {
                Some(rule) => follow(rule, t.step, &state, (&points, gap), slot),
                None => dv,
            };
            let (dx, dy, dth) = (act[3 * f], act[3 * f + 1], act[3 * f + 2]);
            let (co, si) = (dth.cos(), dth.sin());
            let px = v[0] + (v[2] + dvx * 0.5) * t.step - dx;
            let py = v[1] + (v[3] + dvy * 0.5) * t.step - dy;
            let (wx, wy) = (v[2] + dvx, v[3] + dvy);
            let hd = v[4] - dth;
            let pi = std::f32::consts::PI;
            let tau = (2.0 * std::f64::consts::PI) as f32;
            let nv = [
                co * px + si * py,
                co * py - si * px,
                co * wx + si * wy,
                co * wy - si * wx,
                hd - ((hd + pi) / tau).floor() * tau,
            ];
            let stays = nv[0] >= fl[0].lo && nv[0] < fl[0].hi && nv[1] >= fl[1].lo && nv[1] < fl[1].hi;
            if let (Some(pad), false) = (t.pad, stays) {
                o.fill(pad as i32);
                continue;
            }
            for q in 0..5 {
                let b = ((nv[q] - fl[q].lo) / fl[q].width).floor();
                o[fl[q].index] = b.clamp(0.0, (fl[q].bins - 1) as f32) as i32;
            }
        }
    }
    let dst = t.out;
    match x.bufs.get_mut(dst.id as usize) {
        Some((_, super::host::Store::I32(v))) => {
            v[dst.at..dst.at + out.len()].copy_from_slice(&out);
            Ok(())
        }
        _ => Err(ExecError::Invalid("track: the output is not i32".into())),
    }
}

/// One slot of a frame as the track rule reads it: whether it holds an object, its x, y, vx, vy and
/// heading, and its velocity change.
#[derive(Debug, Clone, Copy)]
struct SlotState {
    occupied: bool,
    v: [f32; 5],
    dv: [f32; 2],
}

/// Slot `i`'s velocity change with the braking `rule` asks for over a step of `dt` where it is harder,
/// for the other slots and the standing stop points (x, y, heading) kept `gap` m behind
/// (`backbone::track`'s `follow`, op for op in f32).
fn follow(
    rule: &TrackFollow,
    dt: f32,
    slots: &[SlotState],
    (points, gap): (&[[f32; 3]], f32),
    i: usize,
) -> [f32; 2] {
    let SlotState { v, dv, .. } = slots[i];
    let (c, s) = (v[4].cos(), v[4].sin());
    let speed = v[2] * c + v[3] * s;
    // What leader (x, y, heading) at `closing` m/s with `gap` m between centres asks for, if it leads.
    let need = |[x, y, h]: [f32; 3], closing: f32, gap: f32| {
        let (dx, dy) = (x - v[0], y - v[1]);
        let along = dx * c + dy * s;
        let across = dy * c - dx * s;
        let same_way = h.cos() * c + h.sin() * s;
        let room = (along - gap).max(rule.min_room);
        let need = closing * closing / (room * 2.0);
        let leads =
            along > 0.0 && across.abs() <= rule.half_width && same_way >= rule.cos_heading && closing > 0.0;
        if leads { need } else { 0.0 }
    };
    let mut hardest = 0.0f32;
    for other in slots.iter().filter(|o| o.occupied) {
        let u = other.v;
        let closing = speed - (u[2] * c + u[3] * s);
        hardest = hardest.max(need([u[0], u[1], u[4]], closing, rule.min_gap));
    }
    for &p in points {
        hardest = hardest.max(need(p, speed, gap));
    }
    if hardest < rule.onset {
        return dv;
    }
    let target = (hardest.min(rule.max) * -dt).max(-speed);
    let change = dv[0] * c + dv[1] * s;
    let delta = (target - change).min(0.0);
    [dv[0] + delta * c, dv[1] + delta * s]
}
