//! The engine's device buffers, allocated once per chunk or group size: the window pass's, the ego
//! module's and the decoding step's, and the per-frame tables a control sizes.

use super::{HIDDEN_ROWS, Layout, Sizes};
use crate::error::Result;
use umgen_cuda::ops::{Buf, Elem, Exec, ROWS_SPLIT};

/// The window pass's buffers, for `chunk` scenes of `window` frames.
#[derive(Debug)]
pub(super) struct WindowBufs {
    pub(super) tok: Buf,
    pub(super) act: Buf,
    pub(super) x: Buf,
    pub(super) xn: Buf,
    pub(super) qkv: Buf,
    pub(super) att: Buf,
    pub(super) hid: Buf,
    pub(super) hid_rows: usize,
    pub(super) fresh_tok: Buf,
    pub(super) fresh: Buf,
    /// The flash2 kernels' log-sum-exp rows (not read).
    pub(super) lse: Buf,
    pub(super) map: Option<Buf>,
    pub(super) align_base: Option<Buf>,
    pub(super) track: Option<(Buf, Buf, Buf)>,
    pub(super) ego: Option<EgoBufs>,
}

/// The ego module's buffers.
#[derive(Debug)]
pub(super) struct EgoBufs {
    pub(super) eq: Buf,
    pub(super) qn: Buf,
    pub(super) qf: Buf,
    pub(super) ctx: Buf,
    pub(super) kv: Buf,
    pub(super) y: Buf,
    pub(super) hid: Buf,
    pub(super) logits: Buf,
    /// The attention's split results and counters.
    pub(super) part: Buf,
    pub(super) count: Buf,
}

/// The decoding step's buffers, for `group` scenes.
#[derive(Debug)]
pub(super) struct DecodeBufs {
    pub(super) h: Buf,
    pub(super) xs: Buf,
    pub(super) t1: Buf,
    pub(super) q: Buf,
    pub(super) y: Buf,
    pub(super) hb: Buf,
    pub(super) logits: Buf,
    pub(super) kc: Vec<Buf>,
    pub(super) vc: Vec<Buf>,
    /// The attention's split results and counters, and the split count.
    pub(super) part: Buf,
    pub(super) count: Buf,
    pub(super) splits: usize,
    pub(super) pos: Buf,
    pub(super) done: Buf,
    pub(super) counts: Buf,
    pub(super) state: Buf,
    pub(super) keep_idx: Buf,
    pub(super) tok: Buf,
    pub(super) rules: Buf,
    pub(super) caps: Caps,
    pub(super) tables: Option<Tables>,
}

/// Capacities of the per-frame tables a control sizes: group runs, keep entries, groups, keep logits per
/// scene. Growing one reallocates its table and forgets the captured steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Caps {
    pub(super) runs: usize,
    pub(super) keeps: usize,
    pub(super) groups: usize,
    pub(super) keep_logits: usize,
}

/// The per-frame tables of [`Caps`].
#[derive(Debug, Clone, Copy)]
pub(super) struct Tables {
    pub(super) runs: Buf,
    pub(super) keep_on: Buf,
    pub(super) newborn: Buf,
    pub(super) boxes: Buf,
    pub(super) nboxes: Buf,
    pub(super) keep_logits: Buf,
}

/// A new zeroed buffer.
pub(super) fn alloc<X: Exec>(x: &mut X, elem: Elem, len: usize) -> Result<Buf> {
    Ok(x.alloc(elem, len)?)
}

impl WindowBufs {
    /// Every buffer it holds.
    pub(super) fn bufs(&self) -> Vec<Buf> {
        let mut v = vec![
            self.tok,
            self.act,
            self.x,
            self.xn,
            self.qkv,
            self.att,
            self.hid,
            self.fresh_tok,
            self.fresh,
        ];
        v.extend(self.map.into_iter().chain(self.align_base));
        if let Some((a, b, c)) = self.track {
            v.extend([a, b, c]);
        }
        if let Some(e) = &self.ego {
            v.extend([
                e.eq, e.qn, e.qf, e.ctx, e.kv, e.y, e.hid, e.logits, e.part, e.count,
            ]);
        }
        v
    }

    pub(super) fn new<X: Exec>(
        x: &mut X,
        lay: &Layout,
        m: &Sizes,
        chunk: usize,
        window: usize,
    ) -> Result<Self> {
        let (n, d) = (lay.n, lay.d);
        let frames = chunk * window;
        let rows = frames * n;
        let hid_rows = rows.min(HIDDEN_ROWS);
        let spec = &lay.spec;
        let block = spec
            .action
            .as_ref()
            .map_or(1, |a| spec.segments[a.segment].block_len);
        let map = match &spec.align {
            Some(al) => Some(alloc(x, Elem::F32, frames * al.rows * al.cols * d)?),
            None => None,
        };
        let align_base = match &spec.align {
            Some(al) => {
                let mut base = Vec::with_capacity(al.rows * al.cols * 2);
                for r in 0..al.rows {
                    for c in 0..al.cols {
                        base.push((2.0 * c as f32 + 1.0) / al.cols as f32 - 1.0);
                        base.push((2.0 * r as f32 + 1.0) / al.rows as f32 - 1.0);
                    }
                }
                Some(super::weights::upload(x, Elem::F32, &base)?)
            }
            None => None,
        };
        let track = match (&spec.track, m.track) {
            (Some(t), true) => {
                let l = spec.segments[t.segment].tokens;
                Some((
                    alloc(x, Elem::I32, frames * l)?,
                    alloc(x, Elem::F32, frames * l * d)?,
                    alloc(x, Elem::F32, chunk * l * d)?,
                ))
            }
            _ => None,
        };
        let ego = match m.ego {
            Some((queries, len, vocab)) => {
                let ctx_rows = (window * len).max(n - len);
                let q = chunk * queries;
                let splits = ctx_rows.div_ceil(ROWS_SPLIT);
                Some(EgoBufs {
                    eq: alloc(x, Elem::F32, q * d)?,
                    qn: alloc(x, Elem::W, q * d)?,
                    qf: alloc(x, Elem::F32, q * d)?,
                    ctx: alloc(x, Elem::W, chunk * ctx_rows * d)?,
                    kv: alloc(x, Elem::W, chunk * ctx_rows * 2 * d)?,
                    y: alloc(x, Elem::F32, q * d)?,
                    hid: alloc(x, Elem::W, q * lay.hidden.max(d))?,
                    logits: alloc(x, Elem::F32, q * vocab)?,
                    part: alloc(x, Elem::F32, q * lay.heads * splits * (2 + lay.dh))?,
                    count: alloc(x, Elem::U32, q * lay.heads)?,
                })
            }
            None => None,
        };
        Ok(Self {
            tok: alloc(x, Elem::I32, rows)?,
            act: alloc(x, Elem::F32, frames * 3)?,
            x: alloc(x, Elem::F32, rows * d)?,
            xn: alloc(x, Elem::W, rows * d.max(lay.e))?,
            qkv: alloc(x, Elem::W, rows * 3 * d)?,
            att: alloc(x, Elem::W, rows * d)?,
            hid: alloc(x, Elem::W, hid_rows * lay.hidden.max(d))?,
            hid_rows,
            fresh_tok: alloc(x, Elem::I32, chunk * block)?,
            fresh: alloc(x, Elem::F32, chunk * block * d)?,
            lse: alloc(x, Elem::F32, frames * lay.heads * n)?,
            map,
            align_base,
            track,
            ego,
        })
    }
}

impl DecodeBufs {
    /// Every buffer it holds.
    pub(super) fn bufs(&self) -> Vec<Buf> {
        let mut v = vec![
            self.h,
            self.xs,
            self.t1,
            self.q,
            self.y,
            self.hb,
            self.logits,
            self.part,
            self.count,
            self.pos,
            self.done,
            self.counts,
            self.state,
            self.keep_idx,
            self.tok,
            self.rules,
        ];
        v.extend(self.kc.iter().chain(&self.vc));
        if let Some(t) = self.tables {
            v.extend([t.runs, t.keep_on, t.newborn, t.boxes, t.nboxes, t.keep_logits]);
        }
        v
    }

    pub(super) fn new<X: Exec>(x: &mut X, lay: &Layout, m: &Sizes, group: usize) -> Result<Self> {
        let (n, d) = (lay.n, lay.d);
        let vmax = lay.spec.segments.iter().map(|s| s.vocab).max().unwrap_or(1);
        let cache = group * lay.heads * n * lay.dh;
        let layers = m.layers;
        let splits = n.div_ceil(ROWS_SPLIT);
        Ok(Self {
            h: alloc(x, Elem::F32, group * n * d)?,
            xs: alloc(x, Elem::F32, group * d)?,
            t1: alloc(x, Elem::F32, group * d)?,
            q: alloc(x, Elem::F32, group * d)?,
            y: alloc(x, Elem::F32, group * d)?,
            hb: alloc(x, Elem::F32, group * lay.hidden)?,
            logits: alloc(x, Elem::F32, group * vmax)?,
            kc: (0..layers)
                .map(|_| alloc(x, Elem::W, cache))
                .collect::<Result<_>>()?,
            vc: (0..layers)
                .map(|_| alloc(x, Elem::W, cache))
                .collect::<Result<_>>()?,
            part: alloc(x, Elem::F32, group * lay.heads * splits * (2 + lay.dh))?,
            count: alloc(x, Elem::U32, group * lay.heads)?,
            splits,
            pos: alloc(x, Elem::I32, 1)?,
            done: alloc(x, Elem::U32, 1)?,
            counts: alloc(x, Elem::U32, 2)?,
            state: alloc(x, Elem::U32, 3)?,
            keep_idx: alloc(x, Elem::I32, n)?,
            tok: alloc(x, Elem::I32, group * n)?,
            rules: alloc(x, Elem::Rule, n)?,
            caps: Caps {
                runs: 0,
                keeps: 0,
                groups: 0,
                keep_logits: 0,
            },
            tables: None,
        })
    }
}
