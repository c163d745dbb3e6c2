//! The decoding step as operations (the same for every position of a modality's block, so that a GPU
//! replays it as one graph), and the per-frame tables it reads: the rules, the prefilled tokens, the group
//! runs, the keep and newborn flags, the boxes, the device position.

use super::{Caps, Engine, Tables, alloc};
use crate::error::{GenerateError, Result};
use crate::rules::{FrameControl, FrameRules};
use umgen_backbone::Slot;
use umgen_cuda::ops::{
    AttendRows, BOX_WORDS, Buf, Data, Draw, Elem, Exec, Gemv, GemvIn, GemvOut, GroupRun, Keys, Op, Rule,
};

impl<X: Exec> Engine<X> {
    /// The step of a position of segment `s` for `gs` scenes.
    pub(super) fn step_ops(&self, s: usize, gs: usize) -> Result<Vec<Op>> {
        let (w, dec, lay) = (&self.w, &self.dec, &self.lay);
        let (n, d, hidden) = (lay.n, lay.d, lay.hidden);
        let tables = dec
            .tables
            .ok_or_else(|| GenerateError::Settings("the frame's tables were not prepared".into()))?;
        let gemv = |w_: super::weights::LinearW, input, gelu, output| {
            Op::Gemv(Gemv {
                w: w_.w,
                m: gs,
                n: w_.n,
                k: w_.k,
                input,
                bias: w_.b,
                gelu,
                output,
            })
        };
        let rows = |x: Buf, ld: usize| GemvIn::Rows { x, ld };
        let norm = |x: Buf, n: super::weights::NormW| GemvIn::Norm {
            x,
            ld: d,
            g: n.g,
            b: n.b,
        };
        let mut ops = vec![
            gemv(
                w.fc1,
                GemvIn::Embed {
                    table: w.table,
                    row_base: w.row_base,
                    seg_of: w.seg_of,
                    tok: dec.tok,
                    ntok: n,
                    pos_emb: w.pos_emb,
                    pos: dec.pos,
                },
                true,
                GemvOut::Store { out: dec.t1, ld: d },
            ),
            gemv(
                w.fc2,
                rows(dec.t1, d),
                false,
                GemvOut::Prior {
                    out: dec.xs,
                    ld: d,
                    bos: w.bos,
                    h: dec.h,
                    h_ss: n * d,
                    pos: dec.pos,
                },
            ),
        ];
        let (heads, dh) = (lay.heads, lay.dh);
        for (l, layer) in w.oar.iter().enumerate() {
            ops.push(gemv(
                layer.qkv,
                norm(dec.xs, layer.ln1),
                false,
                GemvOut::Qkv {
                    q: dec.q,
                    ld: d,
                    k: dec.kc[l],
                    v: dec.vc[l],
                    heads,
                    dh,
                    cap: n,
                    pos: dec.pos,
                },
            ));
            ops.push(Op::AttendRows(AttendRows {
                q: dec.q,
                k: dec.kc[l],
                v: dec.vc[l],
                y: dec.y,
                part: dec.part,
                count: dec.count,
                splits: dec.splits,
                keys: Keys::Pos(dec.pos),
                key_cap: n,
                q_sb: d,
                q_sr: d,
                k_sb: heads * n * dh,
                k_sh: n * dh,
                k_sj: dh,
                y_sb: d,
                y_sr: d,
                batches: gs,
                rows: 1,
                heads,
                dh,
                scale: (dh as f32).sqrt().recip(),
            }));
            ops.push(gemv(
                layer.proj,
                rows(dec.y, d),
                false,
                GemvOut::Add { out: dec.xs, ld: d },
            ));
            ops.push(gemv(
                layer.fc,
                norm(dec.xs, layer.ln2),
                true,
                GemvOut::Store {
                    out: dec.hb,
                    ld: hidden,
                },
            ));
            ops.push(gemv(
                layer.fc2,
                rows(dec.hb, hidden),
                false,
                GemvOut::Add { out: dec.xs, ld: d },
            ));
        }
        let head = w.oar_heads[s];
        ops.push(gemv(
            head,
            norm(dec.xs, w.ln_oar),
            false,
            GemvOut::Store {
                out: dec.logits,
                ld: head.n,
            },
        ));
        let smp = self.settings.sampling[s];
        let caps = dec.caps;
        ops.push(Op::Draw(Draw {
            logits: dec.logits,
            keep_logits: tables.keep_logits,
            rules: dec.rules,
            runs: tables.runs,
            keep_on: tables.keep_on,
            newborn: tables.newborn,
            tok: dec.tok,
            pos: dec.pos,
            done: dec.done,
            counts: dec.counts,
            boxes: tables.boxes,
            nboxes: tables.nboxes,
            state: dec.state,
            temperature: smp.temperature,
            top_p: smp.top_p,
            top_p_rest: smp.top_p_rest,
            m: gs,
            n,
            vocab: head.n,
            top_k: smp.top_k,
            keeps: caps.keeps,
            groups: caps.groups,
            box_cap: caps.groups + 1,
            keep_cap: caps.keep_logits,
            run_count: caps.runs,
            key: self.key,
        }));
        Ok(ops)
    }

    /// Writes the frame's tables for scenes `g0..g0 + gs` (actions: each scene's action tokens, forced or
    /// drawn) and resets the position, the counters and the boxes.
    pub(super) fn prepare(
        &mut self,
        rules: &FrameRules,
        control: &FrameControl,
        g0: usize,
        gs: usize,
        action: Option<&[Vec<u32>]>,
        frame: u32,
    ) -> Result<()> {
        let lay = &self.lay;
        let (n, spec) = (lay.n, &lay.spec);
        let view = rules.view(&control.groups);
        // Each run's first group index, and the capacities this frame needs.
        let mut group_base = Vec::with_capacity(control.groups.len());
        let mut total = 0;
        for g in &control.groups {
            group_base.push(total);
            total += g.count;
        }
        let mut keeps = Vec::new();
        let mut keep_len = 0;
        let mut table = vec![Rule::FREE; n];
        let mut tok = vec![0i32; gs * n];
        for (p, slot) in lay.slots.iter().enumerate() {
            let r = &mut table[p];
            let fill = |tok: &mut [i32], id: u32| {
                for b in 0..gs {
                    tok[b * n + p] = id as i32;
                }
            };
            match *slot {
                Slot::Start(s) => {
                    r.known = 1;
                    fill(&mut tok, spec.segments[s].vocab as u32);
                }
                Slot::End(s) => {
                    r.known = 1;
                    fill(&mut tok, spec.segments[s].vocab as u32 + 1);
                }
                Slot::Content(s, i) => {
                    let forced = match (&spec.action, action) {
                        (Some(a), Some(act)) if a.segment == s && i < act[0].len() => Some(act),
                        _ => None,
                    };
                    if let Some(act) = forced {
                        r.known = 1;
                        for (b, a) in act.iter().enumerate() {
                            tok[b * n + p] = a[i] as i32;
                        }
                    } else if let Some(id) = rules.placed[p] {
                        r.known = 1;
                        fill(&mut tok, id);
                    } else if let Some(ids) = &rules.given[p] {
                        r.known = 1;
                        for (b, &id) in ids[g0..g0 + gs].iter().enumerate() {
                            tok[b * n + p] = id as i32;
                        }
                    }
                    if let Some(lim) = rules.limits[p] {
                        r.limit = i32::try_from(lim).unwrap_or(i32::MAX);
                    }
                    if let Some((start, j, gi)) = rules.group[p] {
                        let g = &control.groups[gi];
                        r.gstart = start as i32;
                        r.gj = j as i32;
                        r.grun = gi as i32;
                        r.gindex = (group_base[gi] + (start - g.first) / g.size) as i32;
                        r.finish = i32::from(
                            j + 1 == g.size
                                && g.boxes.is_some()
                                && !(start..=p).any(|q| view.set_by_caller(q)),
                        );
                    }
                    if let Some((pad, _)) = &rules.keep[p] {
                        r.keep = keeps.len() as i32;
                        r.keep_pad = *pad as i32;
                        r.keep_off = keep_len as i32;
                        keeps.push((p, s));
                        keep_len += spec.segments[s].vocab;
                    }
                }
            }
        }
        let need = Caps {
            runs: control.groups.len().max(1),
            keeps: keeps.len().max(1),
            groups: total.max(1),
            keep_logits: keep_len.max(1),
        };
        self.tables(need)?;
        let (dec, caps) = (&self.dec, self.dec.caps);
        let Some(t) = dec.tables else {
            return Err(GenerateError::Settings("the frame's tables were not made".into()));
        };
        let mut keep_on = vec![0u8; gs * caps.keeps];
        let mut newborn = vec![0u8; gs * caps.groups];
        for b in 0..gs {
            for (k, (p, _)) in keeps.iter().enumerate() {
                if let Some((_, scenes)) = &rules.keep[*p] {
                    keep_on[b * caps.keeps + k] = u8::from(scenes[g0 + b]);
                }
            }
            for (gi, g) in control.groups.iter().enumerate() {
                for c in 0..g.count {
                    let start = g.first + c * g.size;
                    newborn[b * caps.groups + group_base[gi] + c] = u8::from(rules.newborn[g0 + b][start]);
                }
            }
        }
        let runs: Vec<GroupRun> = if control.groups.is_empty() {
            vec![GroupRun::EMPTY]
        } else {
            control.groups.iter().map(group_run).collect()
        };
        let ego = control
            .groups
            .iter()
            .find_map(|g| g.boxes.as_ref().map(|b| b.ego))
            .unwrap_or([0.0, 0.0]);
        let mut boxes = vec![0.0f64; gs * (caps.groups + 1) * BOX_WORDS];
        for b in 0..gs {
            let at = b * (caps.groups + 1) * BOX_WORDS;
            boxes[at..at + 5].copy_from_slice(&[0.0, 0.0, 0.0, ego[0], ego[1]]);
        }
        let x = &mut self.x;
        x.write(dec.rules, Data::Rules(&table))?;
        x.write(dec.tok, Data::I32(&tok))?;
        x.write(t.runs, Data::Runs(&runs))?;
        x.write(t.keep_on, Data::U8(&keep_on))?;
        x.write(t.newborn, Data::U8(&newborn))?;
        x.write(t.boxes, Data::F64(&boxes))?;
        x.write(t.nboxes, Data::I32(&vec![1; gs]))?;
        x.write(dec.pos, Data::I32(&[0]))?;
        x.write(dec.done, Data::U32(&[0]))?;
        x.write(dec.counts, Data::U32(&[0, 0]))?;
        x.write(dec.state, Data::U32(&[frame, caps.keep_logits as u32, g0 as u32]))?;
        let idx: Vec<i32> = keeps.iter().map(|(p, _)| *p as i32).collect();
        if !idx.is_empty() {
            x.write(dec.keep_idx, Data::I32(&idx))?;
        }
        self.keeps = keeps;
        Ok(())
    }

    /// Makes the per-frame tables hold at least `need` (growing them forgets the captured steps).
    fn tables(&mut self, need: Caps) -> Result<()> {
        let old = self.dec.caps;
        if self.dec.tables.is_some()
            && need.runs <= old.runs
            && need.keeps <= old.keeps
            && need.groups <= old.groups
            && need.keep_logits <= old.keep_logits
        {
            return Ok(());
        }
        let caps = Caps {
            runs: need.runs.max(old.runs),
            keeps: need.keeps.max(old.keeps),
            groups: need.groups.max(old.groups),
            keep_logits: need.keep_logits.max(old.keep_logits),
        };
        let g = self.group;
        let x = &mut self.x;
        if let Some(t) = self.dec.tables.take() {
            for b in [t.runs, t.keep_on, t.newborn, t.boxes, t.nboxes, t.keep_logits] {
                x.free(b.id);
            }
        }
        self.dec.tables = Some(Tables {
            runs: alloc(x, Elem::Run, caps.runs)?,
            keep_on: alloc(x, Elem::U8, g * caps.keeps)?,
            newborn: alloc(x, Elem::U8, g * caps.groups)?,
            boxes: alloc(x, Elem::F64, g * (caps.groups + 1) * BOX_WORDS)?,
            nboxes: alloc(x, Elem::I32, g)?,
            keep_logits: alloc(x, Elem::F32, g * caps.keep_logits)?,
        });
        self.dec.caps = caps;
        self.invalidate();
        Ok(())
    }
}

/// A group run as the draw reads it.
fn group_run(g: &crate::rules::TokenGroups) -> GroupRun {
    let mut run = GroupRun {
        size: g.size as i32,
        pad: g.pad as i32,
        values: g.values as i32,
        last_lo: g.last.start as i32,
        last_hi: g.last.end as i32,
        ..GroupRun::EMPTY
    };
    if let Some(b) = &g.boxes {
        run.boxes = if b.whole_frame { 2 } else { 1 };
        run.max_boxes = i32::try_from(b.max_boxes).unwrap_or(i32::MAX);
        for (f, (i, lo, hi, bins)) in b.fields.iter().enumerate() {
            run.field[f] = *i as i32;
            run.bins[f] = *bins as i32;
            run.lo[f] = *lo;
            run.hi[f] = *hi;
        }
    }
    run
}
