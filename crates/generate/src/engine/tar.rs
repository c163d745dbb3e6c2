//! The TAR's input and layers: the next action's block, the tracked slots moved ahead and AMA
//! (`Backbone::tar`), one TAR layer over time or within frames, and the TAR heads' logits at the positions
//! a keep rule may redraw.

use super::Engine;
use super::weights::SelfW;
use super::window::{Map, Over};
use crate::error::{GenerateError, Result};
use umgen_backbone::{SegmentSpec, StopSpec, TrackSpec};
use umgen_cuda::ops::{
    Align, AttendTiles, BiasT, Buf, Data, Exec, Flash, Op, Rows, Shift, Strides, Track, TrackField,
    TrackFollow, TrackStops,
};

impl<X: Exec> Engine<X> {
    /// The TAR input's parts that follow the next action `act` of each scene of `part` (window `w`): frame
    /// t's action block becomes frame t + 1's (the last the new frame's), the tracked slots moved ahead
    /// enter at their positions, and AMA moves each frame's map.
    pub(super) fn next_action(&mut self, part: &[Vec<Vec<u32>>], act: &[Vec<u32>], w: usize) -> Result<()> {
        let spec = self.lay.spec.clone();
        let Some(a) = spec.action.as_ref() else {
            return Ok(());
        };
        let (n, d, cs, x) = (self.lay.n, self.lay.d, part.len(), self.win.x);
        let t = part[0].len();
        let seg = &spec.segments[a.segment];
        // The new frame's action block: its boundary tokens and the action.
        let block: Vec<i32> = act
            .iter()
            .flat_map(|ids| {
                (seg.block_start..seg.block_start + seg.block_len).map(move |p| {
                    if p < seg.offset {
                        seg.vocab as i32
                    } else if p >= seg.offset + seg.tokens {
                        seg.vocab as i32 + 1
                    } else {
                        ids.get(p - seg.offset).map_or(0, |&i| i as i32)
                    }
                })
            })
            .collect();
        let (fresh_tok, fresh) = (self.win.fresh_tok, self.win.fresh);
        self.x.write(fresh_tok, Data::I32(&block))?;
        self.embed(
            fresh_tok,
            cs * seg.block_len,
            seg.block_len,
            seg.block_start,
            fresh,
        )?;
        self.run(&Op::Shift(Shift {
            x,
            fresh,
            m: cs,
            w,
            n,
            d,
            start: seg.block_start,
            len: seg.block_len,
        }))?;
        // Each window frame's next action, decoded to bin centres in f32 as `Backbone::decode_action`.
        let lo: Vec<f32> = a.bins.iter().map(|b| b.0 as f32).collect();
        let width: Vec<f32> = a
            .bins
            .iter()
            .map(|b| ((b.1 - b.0) / f64::from(b.2)) as f32)
            .collect();
        let mut values = Vec::with_capacity(cs * w * 3);
        for (h, own) in part.iter().zip(act) {
            for f in t - w..t {
                let ids = if f + 1 < t {
                    &h[f + 1][seg.offset..seg.offset + 3]
                } else {
                    &own[..3]
                };
                for k in 0..3 {
                    values.push((ids[k] as f32 + 0.5) * width[k] + lo[k]);
                }
            }
        }
        let actb = self.win.act;
        self.x.write(actb, Data::F32(&values))?;
        if let (Some(k), Some((moved, tmp, moved_out)), Some((in_proj, out_proj))) =
            (&spec.track, self.win.track, self.w.track)
        {
            let ts = &spec.segments[k.segment];
            let l = ts.tokens;
            let op = track_op(k, &spec.segments, [self.win.tok, actb, moved], cs * w, w, n);
            self.run(&Op::Track(op))?;
            self.embed(moved, cs * w * l, l, ts.offset, tmp)?;
            let xn = self.win.xn;
            self.rows(
                Map::packed(tmp, d),
                Map::packed(xn, d),
                cs * w * l,
                1,
                None,
                None,
                false,
            )?;
            // The output projection of each scene's last frame, kept for `h`.
            for s in 0..cs {
                self.gemm(
                    (xn.at((s * w + w - 1) * l * d), d),
                    out_proj,
                    (moved_out.at(s * l * d), d),
                    l,
                    false,
                )?;
            }
            self.gemm((xn, d), in_proj, (tmp, d), cs * w * l, false)?;
            let dst = Map {
                base: x.at(ts.offset * d),
                s1: n * d,
                s2: d,
            };
            self.rows(
                Map {
                    base: tmp,
                    s1: l * d,
                    s2: d,
                },
                dst,
                cs * w * l,
                l,
                None,
                in_proj.b,
                true,
            )?;
        }
        if let (Some(al), Some(map), Some(base)) = (&spec.align, self.win.map, self.win.align_base) {
            let ms = &spec.segments[al.segment];
            let cells = al.rows * al.cols;
            let src = Map {
                base: x.at(ms.offset * d),
                s1: n * d,
                s2: d,
            };
            self.rows(
                src,
                Map {
                    base: map,
                    s1: cells * d,
                    s2: d,
                },
                cs * w * cells,
                cells,
                None,
                None,
                false,
            )?;
            self.run(&Op::Align(Align {
                x,
                src: map,
                act: actb,
                base,
                frames: cs * w,
                n,
                d,
                offset: ms.offset,
                rows: al.rows,
                cols: al.cols,
                tx_scale: (-2.0 / (al.cols as f64 * al.cell_m)) as f32,
                ty_scale: (-2.0 / (al.rows as f64 * al.cell_m)) as f32,
            }))?;
        }
        Ok(())
    }

    /// One TAR layer over the chunk's `cs` scenes of `w` frames in `win.x`.
    pub(super) fn self_layer(&mut self, l: &SelfW, cs: usize, w: usize, over: Over) -> Result<()> {
        let (n, d, heads, dh) = (self.lay.n, self.lay.d, self.lay.heads, self.lay.dh);
        let (x, xn, qkv, att) = (self.win.x, self.win.xn, self.win.qkv, self.win.att);
        let rows = cs * w * n;
        self.rows(
            Map::packed(x, d),
            Map::packed(xn, d),
            rows,
            1,
            Some(l.ln1),
            None,
            false,
        )?;
        self.gemm((xn, d), l.qkv, (qkv, 3 * d), rows, false)?;
        if let Some(b) = l.qkv.b {
            self.run(&Op::BiasT(BiasT {
                x: qkv,
                bias: b,
                rows,
                cols: 3 * d,
                ld: 3 * d,
                gelu: false,
            }))?;
        }
        if matches!(over, Over::Frame) && self.x.flash(dh) {
            // FlashAttention-2 on the tensor cores, each frame a batch entry.
            let qs = [n * 3 * d, dh, 3 * d];
            self.run(&Op::Flash(Flash {
                q: qkv,
                k: qkv.at(d),
                v: qkv.at(2 * d),
                y: att,
                lse: self.win.lse,
                qs,
                ks: qs,
                vs: qs,
                ys: [n * d, dh, d],
                batch: cs * w,
                heads,
                lq: n,
                lk: n,
                dh,
                causal: false,
            }))?;
            return self.layer_tail(l, rows);
        }
        let (instances, inner, qs, ys, len, causal) = match over {
            // Instance (scene, position), rows the frames.
            Over::Time => (
                cs * n,
                n,
                Strides {
                    s1: w * n * 3 * d,
                    s2: 3 * d,
                    row: n * 3 * d,
                },
                Strides {
                    s1: w * n * d,
                    s2: d,
                    row: n * d,
                },
                w,
                Some(0),
            ),
            // Instance the frame, rows its positions.
            Over::Frame => (
                cs * w,
                1,
                Strides {
                    s1: n * 3 * d,
                    s2: 0,
                    row: 3 * d,
                },
                Strides {
                    s1: n * d,
                    s2: 0,
                    row: d,
                },
                n,
                None,
            ),
        };
        self.run(&Op::AttendTiles(AttendTiles {
            q: qkv,
            k: qkv.at(d),
            v: qkv.at(2 * d),
            y: att,
            qs,
            ks: qs,
            ys,
            instances,
            inner,
            heads,
            lq: len,
            lk: len,
            dh,
            causal,
            scale: (dh as f32).sqrt().recip(),
        }))?;
        self.layer_tail(l, rows)
    }

    /// The rest of a TAR layer once its attention is in `win.att`: the output projection and the MLP, each
    /// added to the residual stream.
    fn layer_tail(&mut self, l: &SelfW, rows: usize) -> Result<()> {
        let (d, x, xn, att) = (self.lay.d, self.win.x, self.win.xn, self.win.att);
        self.gemm((att, d), l.proj, (x, d), rows, true)?;
        self.rows(
            Map::packed(x, d),
            Map::packed(x, d),
            rows,
            1,
            None,
            l.proj.b,
            false,
        )?;
        self.rows(
            Map::packed(x, d),
            Map::packed(xn, d),
            rows,
            1,
            Some(l.ln2),
            None,
            false,
        )?;
        self.mlp((xn, d), (l.fc, l.fc2), x, rows, true)
    }

    /// The TAR heads' logits at the frame's keep positions for the group's `gs` scenes (`h` ready), into
    /// the keep rows at each entry's offset.
    pub(super) fn keep_logits(&mut self, gs: usize) -> Result<()> {
        let Some(tables) = self.dec.tables else {
            return Err(GenerateError::Settings("the frame's tables were not made".into()));
        };
        let (n, d, cap) = (self.lay.n, self.lay.d, self.dec.caps.keep_logits);
        let keeps = self.keeps.clone();
        let xn = self.win.xn;
        let mut first = 0;
        while first < keeps.len() {
            // The entries of one segment are consecutive (segments are blocks of positions).
            let s = keeps[first].1;
            let count = keeps[first..].iter().take_while(|(_, t)| *t == s).count();
            let offset: usize = keeps[..first]
                .iter()
                .map(|(_, t)| self.lay.spec.segments[*t].vocab)
                .sum();
            self.run(&Op::Rows(Rows {
                src: self.dec.h,
                idx: Some(self.dec.keep_idx.at(first)),
                dst: xn,
                norm: None,
                bias: None,
                src_s1: n * d,
                src_s2: d,
                period: 0,
                dst_s1: count * d,
                dst_s2: d,
                rows: gs * count,
                inner: count,
                d,
                add: false,
                gelu: false,
            }))?;
            let head = self.w.tar_heads[s];
            for b in 0..gs {
                self.gemm(
                    (xn.at(b * count * d), d),
                    head,
                    (tables.keep_logits.at(b * cap + offset), head.n),
                    count,
                    false,
                )?;
            }
            first += count;
        }
        Ok(())
    }
}

/// The `track` operation moving the slots of `k` (of its segment among `segments`) one frame ahead, over
/// `frames` frames of `n` positions in windows of `w`: the window's tokens `tok`, each frame's next action
/// `act`, the moved ids into `out`. The spec's bins, follow rule and stop points in f32, as burn's
/// operations take them.
pub fn track_op(
    k: &TrackSpec,
    segments: &[SegmentSpec],
    [tok, act, out]: [Buf; 3],
    frames: usize,
    w: usize,
    n: usize,
) -> Track {
    let seg = &segments[k.segment];
    Track {
        tok,
        act,
        out,
        frames,
        w,
        n,
        offset: seg.offset,
        slots: seg.tokens / k.slot,
        k: k.slot,
        values: k.values,
        pad: k.pad,
        accel: k.accel,
        fields: k.fields.map(track_field),
        step: k.step_s as f32,
        follow: k.follow.map(|f| TrackFollow {
            half_width: f.half_width_m as f32,
            cos_heading: f.cos_heading as f32,
            min_gap: f.min_gap_m as f32,
            min_room: f.min_room_m as f32,
            onset: f.onset_m_s2 as f32,
            max: f.max_m_s2 as f32,
        }),
        stops: k.stops.as_ref().and_then(|st| stops_op(st, segments)),
    }
}

// The kernels' id arrays hold every id a validated spec has.
const _: () = assert!(umgen_backbone::STOP_IDS == umgen_cuda::ops::TRACK_STOP_IDS);

/// The stop points of `st` for the `track` operation; `None` when its segment is not in `segments`
/// (a spec that validated has it).
fn stops_op(st: &StopSpec, segments: &[SegmentSpec]) -> Option<TrackStops> {
    let seg = segments.get(st.segment)?;
    let ids = |v: &[u32]| std::array::from_fn(|i| v.get(i).map_or(-1, |&id| id as i32));
    Some(TrackStops {
        offset: seg.offset,
        slots: seg.tokens / st.slot,
        k: st.slot,
        values: st.values,
        fields: st.fields.map(track_field),
        state: st.state,
        stop: ids(&st.stop),
        go: ids(&st.go),
        gap: st.gap_m as f32,
    })
}

/// A binned field `(slot position, (lo, hi, bins))` in f32, its width computed in f64 as burn's scalar.
fn track_field((index, (lo, hi, bins)): (usize, (f64, f64, u32))) -> TrackField {
    TrackField {
        index,
        lo: lo as f32,
        hi: hi as f32,
        bins,
        width: ((hi - lo) / f64::from(bins)) as f32,
    }
}
