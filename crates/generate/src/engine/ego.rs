//! The ego module on the window's embeddings (`EgoModule::forward` with `last_only`): learned queries (plus
//! each scene's latest action) attend to every window frame's action block (CA_hist), then to the last
//! frame's other blocks (CA_env); the head's logits are read back and drawn on the host.

use super::Engine;
use super::window::Map;
use crate::error::Result;
use umgen_cuda::ops::{AttendRows, BiasT, Exec, Keys, Op, ROWS_SPLIT};

impl<X: Exec> Engine<X> {
    /// The ego module's action tokens for the chunk's `cs` scenes (window `w`, embedded in `win.x`), drawn on
    /// the host from its logits in scene order; `None` without an ego module.
    pub(super) fn ego_action(&mut self, cs: usize, w: usize) -> Result<Option<Vec<Vec<u32>>>> {
        let (Some(eg), Some(buf), Some(a)) = (
            self.w.ego.clone(),
            self.win
                .ego
                .as_ref()
                .map(|e| (e.eq, e.qn, e.qf, e.ctx, e.kv, e.y, e.logits, (e.part, e.count))),
            self.lay.spec.action.clone(),
        ) else {
            return Ok(None);
        };
        let (eq, qn, qf, ctx, kv, y, logits, (part, count)) = buf;
        let (n, d, x) = (self.lay.n, self.lay.d, self.win.x);
        let (q, [bs, len]) = (eg.q, eg.block);
        let rows = cs * q;
        // The queries, plus each scene's own latest action (`ego_last`).
        self.rows(
            Map {
                base: eg.queries,
                s1: 0,
                s2: d,
            },
            Map {
                base: eq,
                s1: q * d,
                s2: d,
            },
            rows,
            q,
            None,
            None,
            false,
        )?;
        if let Some(at) = eg.last {
            let src = Map {
                base: x.at(((w - 1) * n + at) * d),
                s1: w * n * d,
                s2: d,
            };
            self.rows(
                src,
                Map {
                    base: eq,
                    s1: q * d,
                    s2: d,
                },
                rows,
                q,
                None,
                None,
                true,
            )?;
        }
        for (layers, hist) in [(&eg.hist, true), (&eg.env, false)] {
            // The context: every frame's action block (CA_hist), or the last frame's other blocks (CA_env).
            let lc = if hist { w * len } else { n - len };
            for l in layers {
                self.rows(
                    Map::packed(eq, d),
                    Map::packed(qn, d),
                    rows,
                    1,
                    Some(l.ln_q),
                    None,
                    false,
                )?;
                self.gemm((qn, d), l.q, (qf, d), rows, false)?;
                self.rows(
                    Map::packed(qf, d),
                    Map::packed(qf, d),
                    rows,
                    1,
                    None,
                    l.q.b,
                    false,
                )?;
                let ctx_rows = if hist {
                    let src = Map {
                        base: x.at(bs * d),
                        s1: n * d,
                        s2: d,
                    };
                    let dst = Map {
                        base: ctx,
                        s1: len * d,
                        s2: d,
                    };
                    self.rows(src, dst, cs * w * len, len, Some(l.ln_ctx), None, false)?;
                    cs * w * len
                } else {
                    let last = x.at((w - 1) * n * d);
                    let before = Map {
                        base: last,
                        s1: w * n * d,
                        s2: d,
                    };
                    self.rows(
                        before,
                        Map {
                            base: ctx,
                            s1: lc * d,
                            s2: d,
                        },
                        cs * bs,
                        bs.max(1),
                        Some(l.ln_ctx),
                        None,
                        false,
                    )?;
                    let rest = n - bs - len;
                    let after = Map {
                        base: last.at((bs + len) * d),
                        s1: w * n * d,
                        s2: d,
                    };
                    self.rows(
                        after,
                        Map {
                            base: ctx.at(bs * d),
                            s1: lc * d,
                            s2: d,
                        },
                        cs * rest,
                        rest.max(1),
                        Some(l.ln_ctx),
                        None,
                        false,
                    )?;
                    cs * lc
                };
                self.gemm((ctx, d), l.kv, (kv, 2 * d), ctx_rows, false)?;
                if let Some(b) = l.kv.b {
                    self.run(&Op::BiasT(BiasT {
                        x: kv,
                        bias: b,
                        rows: ctx_rows,
                        cols: 2 * d,
                        ld: 2 * d,
                        gelu: false,
                    }))?;
                }
                let (heads, dh) = (self.lay.heads, self.lay.dh);
                self.run(&Op::AttendRows(AttendRows {
                    q: qf,
                    k: kv,
                    v: kv.at(d),
                    y,
                    part,
                    count,
                    splits: lc.div_ceil(ROWS_SPLIT),
                    keys: Keys::Fixed(lc),
                    key_cap: lc,
                    q_sb: q * d,
                    q_sr: d,
                    k_sb: lc * 2 * d,
                    k_sh: dh,
                    k_sj: 2 * d,
                    y_sb: q * d,
                    y_sr: d,
                    batches: cs,
                    rows: q,
                    heads,
                    dh,
                    scale: (dh as f32).sqrt().recip(),
                }))?;
                self.rows(Map::packed(y, d), Map::packed(qn, d), rows, 1, None, None, false)?;
                self.gemm((qn, d), l.proj, (eq, d), rows, true)?;
                self.rows(
                    Map::packed(eq, d),
                    Map::packed(eq, d),
                    rows,
                    1,
                    None,
                    l.proj.b,
                    false,
                )?;
                self.rows(
                    Map::packed(eq, d),
                    Map::packed(qn, d),
                    rows,
                    1,
                    Some(l.ln2),
                    None,
                    false,
                )?;
                let hid = self.win.ego.as_ref().map_or(qn, |e| e.hid);
                self.gemm((qn, d), l.fc, (hid, l.fc.n), rows, false)?;
                if let Some(b) = l.fc.b {
                    self.run(&Op::BiasT(BiasT {
                        x: hid,
                        bias: b,
                        rows,
                        cols: l.fc.n,
                        ld: l.fc.n,
                        gelu: true,
                    }))?;
                }
                self.gemm((hid, l.fc.n), l.fc2, (eq, d), rows, true)?;
                self.rows(
                    Map::packed(eq, d),
                    Map::packed(eq, d),
                    rows,
                    1,
                    None,
                    l.fc2.b,
                    false,
                )?;
            }
        }
        self.rows(
            Map::packed(eq, d),
            Map::packed(qn, d),
            rows,
            1,
            Some(eg.ln),
            None,
            false,
        )?;
        let v = eg.head.n;
        self.gemm((qn, d), eg.head, (logits, v), rows, false)?;
        let host = self.x.read_f32(logits, rows * v)?;
        let smp = self.settings.sampling[a.segment];
        let rng = &mut self.rng;
        Ok(Some(
            host.chunks(q * v)
                .map(|scene| scene.chunks(v).map(|l| smp.draw(l, rng)).collect())
                .collect(),
        ))
    }
}
