//! The window pass: embeddings of the history, the ego module (`ego.rs`), the TAR input and layers
//! (`tar.rs`), and the prior `h` of the new frame, as `Backbone::tar` and the burn decoder's `window_pass`
//! compute them; and the row, product and MLP helpers the other parts share.

use super::Engine;
use super::weights::{LinearW, NormW};
use crate::error::Result;
use umgen_cuda::ops::{BiasT, Buf, Data, Embed, Exec, Gemm, Op, Rows};

/// A row mapping of [`Rows`]: row r is (r / inner, r % inner) at `base + i1·s1 + i2·s2`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Map {
    pub(super) base: Buf,
    pub(super) s1: usize,
    pub(super) s2: usize,
}

impl Map {
    /// Rows of width `d` one after another (with one row per outer index: `inner` 1).
    pub(super) fn packed(base: Buf, d: usize) -> Self {
        Self { base, s1: d, s2: 0 }
    }
}

/// Which attention a TAR layer runs.
#[derive(Debug, Clone, Copy)]
pub(super) enum Over {
    /// Each position over its own frames (causal).
    Time,
    /// Each frame's positions (bidirectional).
    Frame,
}

impl<X: Exec> Engine<X> {
    /// `dst[r] (+)= norm?(src[r]) + bias` over `rows` rows of width `d` (`inner` rows per outer index).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn rows(
        &mut self,
        src: Map,
        dst: Map,
        rows: usize,
        inner: usize,
        norm: Option<NormW>,
        bias: Option<Buf>,
        add: bool,
    ) -> Result<()> {
        self.rows_d(src, dst, rows, inner, self.lay.d, norm, bias, add)
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn rows_d(
        &mut self,
        src: Map,
        dst: Map,
        rows: usize,
        inner: usize,
        d: usize,
        norm: Option<NormW>,
        bias: Option<Buf>,
        add: bool,
    ) -> Result<()> {
        if rows == 0 {
            return Ok(());
        }
        self.run(&Op::Rows(Rows {
            src: src.base,
            idx: None,
            dst: dst.base,
            norm: norm.map(|n| (n.g, n.b)),
            bias,
            src_s1: src.s1,
            src_s2: src.s2,
            period: 0,
            dst_s1: dst.s1,
            dst_s2: dst.s2,
            rows,
            inner,
            d,
            add,
            gelu: false,
        }))
    }

    /// `c (+)= a · l.wᵀ` over `rows` rows (no bias).
    pub(super) fn gemm(
        &mut self,
        (a, lda): (Buf, usize),
        l: LinearW,
        (c, ldc): (Buf, usize),
        rows: usize,
        accumulate: bool,
    ) -> Result<()> {
        if rows == 0 {
            return Ok(());
        }
        self.run(&Op::Gemm(Gemm {
            a,
            w: l.w,
            c,
            rows,
            n: l.n,
            k: l.k,
            lda,
            ldc,
            accumulate,
        }))
    }

    /// `x += gelu(xn · fc + b) · fc2` (+ fc2's bias) over `rows` rows of `xn` (`W`, `ld` apart) into the f32
    /// rows `out` (`d` apart), a slice of the hidden buffer's rows at a time; without `accumulate`, `out =`.
    pub(super) fn mlp(
        &mut self,
        (xn, ld): (Buf, usize),
        (fc, fc2): (LinearW, LinearW),
        out: Buf,
        rows: usize,
        accumulate: bool,
    ) -> Result<()> {
        let (d, hid, cap) = (self.lay.d, self.win.hid, self.win.hid_rows);
        for r0 in (0..rows).step_by(cap) {
            let r = cap.min(rows - r0);
            self.gemm((xn.at(r0 * ld), ld), fc, (hid, fc.n), r, false)?;
            if let Some(b) = fc.b {
                self.run(&Op::BiasT(BiasT {
                    x: hid,
                    bias: b,
                    rows: r,
                    cols: fc.n,
                    ld: fc.n,
                    gelu: true,
                }))?;
            }
            self.gemm((hid, fc.n), fc2, (out.at(r0 * d), d), r, accumulate)?;
        }
        let packed = Map::packed(out, d);
        self.rows(packed, packed, rows, 1, None, fc2.b, false)
    }

    /// Token embeddings of `rows` tokens in `tok` at positions `p0 + r % period` into f32 rows `out`.
    pub(super) fn embed(&mut self, tok: Buf, rows: usize, period: usize, p0: usize, out: Buf) -> Result<()> {
        let (w, xn, e) = (&self.w, self.win.xn, self.lay.e);
        let op = Op::Embed(Embed {
            table: w.table,
            row_base: w.row_base,
            seg_of: w.seg_of,
            tok,
            pos_emb: w.pos_emb,
            out: xn,
            rows,
            period,
            p0,
            e,
        });
        let (fc1, fc2) = (w.fc1, w.fc2);
        self.run(&op)?;
        self.mlp((xn, e), (fc1, fc2), out, rows, false)
    }

    /// The prior of the new frame of scenes `hist` (one group) into the decoding buffers' `h` rows, and
    /// each scene's action tokens (`forced`, or drawn from the ego module on the host).
    pub(super) fn window_pass(
        &mut self,
        hist: &[Vec<Vec<u32>>],
        forced: Option<&[Vec<u32>]>,
    ) -> Result<Option<Vec<Vec<u32>>>> {
        let (n, d) = (self.lay.n, self.lay.d);
        let gs = hist.len();
        let t = hist.first().map_or(0, Vec::len);
        if t == 0 {
            // An initial scene: no history, no TAR (as in the paper).
            self.x.write(self.dec.h, Data::F32(&vec![0.0; gs * n * d]))?;
            return Ok(forced.map(<[Vec<u32>]>::to_vec));
        }
        let w = t.min(self.settings.window);
        let mut actions = Vec::new();
        for c0 in (0..gs).step_by(self.chunk) {
            let cs = self.chunk.min(gs - c0);
            let part = &hist[c0..c0 + cs];
            let tok: Vec<i32> = part
                .iter()
                .flat_map(|h| h[t - w..].iter().flatten().map(|&id| id as i32))
                .collect();
            self.x.write(self.win.tok, Data::I32(&tok))?;
            let (tokw, x) = (self.win.tok, self.win.x);
            self.embed(tokw, cs * w * n, n, 0, x)?;
            let act = match forced {
                Some(f) => Some(f[c0..c0 + cs].to_vec()),
                None => self.ego_action(cs, w)?,
            };
            if let Some(act) = &act {
                self.next_action(part, act, w)?;
            }
            // The frame embedding, added to every position of frame t.
            let time = self.w.time;
            self.run(&Op::Rows(Rows {
                src: time,
                idx: None,
                dst: x,
                norm: None,
                bias: None,
                src_s1: d,
                src_s2: 0,
                period: w,
                dst_s1: n * d,
                dst_s2: d,
                rows: cs * w * n,
                inner: n,
                d,
                add: true,
                gelu: false,
            }))?;
            let layers = self.w.tar.clone();
            for (temporal, spatial) in &layers {
                self.self_layer(temporal, cs, w, Over::Time)?;
                self.self_layer(spatial, cs, w, Over::Frame)?;
            }
            // h: the last frame's rows through the TAR's norm, into the group's rows.
            let src = Map {
                base: x.at((w - 1) * n * d),
                s1: w * n * d,
                s2: d,
            };
            let dst = Map {
                base: self.dec.h.at(c0 * n * d),
                s1: n * d,
                s2: d,
            };
            let ln = self.w.ln_tar;
            self.rows(src, dst, cs * n, n, Some(ln), None, false)?;
            if let (Some(spec), Some((_, out_proj)), Some((_, _, moved_out)), Some(_)) = (
                self.lay.spec.track.clone(),
                self.w.track,
                self.win.track,
                act.as_ref(),
            ) {
                let (l, offset) = (
                    self.lay.spec.segments[spec.segment].tokens,
                    self.lay.spec.segments[spec.segment].offset,
                );
                let dst = Map {
                    base: self.dec.h.at(c0 * n * d + offset * d),
                    s1: n * d,
                    s2: d,
                };
                self.rows(
                    Map {
                        base: moved_out,
                        s1: l * d,
                        s2: d,
                    },
                    dst,
                    cs * l,
                    l,
                    None,
                    out_proj.b,
                    true,
                )?;
            }
            if let Some(a) = act {
                actions.extend(a);
            }
        }
        Ok((!actions.is_empty()).then_some(actions))
    }
}
