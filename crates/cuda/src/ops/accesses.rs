//! What each operation reaches: for every buffer it names, the types it takes and one past the last
//! element it reads or writes from the buffer's start, and the sizes its kernel takes. Elements that
//! depend on device data (a table row chosen by a token, the cache slot of the device position) are
//! bounded by the engine's invariants instead: tokens stay inside their vocabularies, the position
//! inside the frame.

use super::{
    BOX_WORDS, Buf, DRAW_KMAX, Elem, ExecError, GEMV_ROWS, GemvIn, GemvOut, Keys, MAX_HEAD, Op,
    ROWS_MAX_SPLITS, ROWS_SPLIT, Strides,
};

/// One buffer an operation reaches.
#[derive(Debug, Clone, Copy)]
pub struct Access {
    /// The buffer.
    pub buf: Buf,
    /// One past the last element reached, from `buf.at`.
    pub end: usize,
    /// The types it may hold.
    pub kinds: &'static [Elem],
    /// The operand's name.
    pub what: &'static str,
}

const F32: &[Elem] = &[Elem::F32];
const W: &[Elem] = &[Elem::W];
const EITHER: &[Elem] = &[Elem::F32, Elem::W];
const I32: &[Elem] = &[Elem::I32];
const U32: &[Elem] = &[Elem::U32];
const U8: &[Elem] = &[Elem::U8];

/// One past the last element of `count` items `stride` apart, each `tail` long (0 for no items).
fn span(items: &[(usize, usize)], tail: usize) -> usize {
    if items.iter().any(|(count, _)| *count == 0) {
        return 0;
    }
    items
        .iter()
        .map(|(count, stride)| (count - 1) * stride)
        .sum::<usize>()
        + tail
}

/// The largest element offset of an attention operand: instances split by `inner`, `rows` rows.
fn tiles_span(s: &Strides, instances: usize, inner: usize, rows: usize, heads: usize, dh: usize) -> usize {
    let outer = instances.div_ceil(inner.max(1));
    span(
        &[
            (outer, s.s1),
            (inner.min(instances), s.s2),
            (rows, s.row),
            (heads, dh),
        ],
        dh,
    )
}

fn invalid(op: &Op, why: String) -> ExecError {
    ExecError::Invalid(format!("{}: {why}", op.name()))
}

/// Whether `b` starts on 16 bytes whatever the element type (a multiple of 8 elements).
fn aligned(b: Buf) -> bool {
    b.at.is_multiple_of(8)
}

impl Op {
    /// Every buffer it reaches.
    pub fn accesses(&self) -> Vec<Access> {
        let a = |buf: Buf, end: usize, kinds: &'static [Elem], what: &'static str| Access {
            buf,
            end,
            kinds,
            what,
        };
        match self {
            Op::Gemv(g) => {
                let mut v = vec![a(g.w, g.n * g.k, W, "w")];
                match &g.input {
                    GemvIn::Rows { x, ld } => v.push(a(*x, span(&[(g.m, *ld)], g.k), F32, "x")),
                    GemvIn::Norm { x, ld, g: s, b } => v.extend([
                        a(*x, span(&[(g.m, *ld)], g.k), F32, "x"),
                        a(*s, g.k, F32, "norm scale"),
                        a(*b, g.k, F32, "norm shift"),
                    ]),
                    GemvIn::Embed {
                        table,
                        row_base,
                        seg_of,
                        tok,
                        ntok,
                        pos_emb,
                        pos,
                    } => v.extend([
                        a(*table, g.k, F32, "table"),
                        a(*row_base, 1, I32, "row_base"),
                        a(*seg_of, 1, I32, "seg_of"),
                        a(*tok, g.m * ntok, I32, "tok"),
                        a(*pos_emb, g.k, F32, "pos_emb"),
                        a(*pos, 1, I32, "pos"),
                    ]),
                }
                if let Some(b) = g.bias {
                    v.push(a(b, g.n, F32, "bias"));
                }
                match &g.output {
                    GemvOut::Store { out, ld } | GemvOut::Add { out, ld } => {
                        v.push(a(*out, span(&[(g.m, *ld)], g.n), F32, "out"))
                    }
                    GemvOut::Qkv {
                        q,
                        ld,
                        k,
                        v: vc,
                        heads,
                        dh,
                        cap,
                        pos,
                    } => v.extend([
                        a(*q, span(&[(g.m, *ld)], heads * dh), F32, "q"),
                        a(*k, g.m * heads * cap * dh, W, "key cache"),
                        a(*vc, g.m * heads * cap * dh, W, "value cache"),
                        a(*pos, 1, I32, "pos"),
                    ]),
                    GemvOut::Prior {
                        out,
                        ld,
                        bos,
                        h,
                        h_ss,
                        pos,
                    } => v.extend([
                        a(*out, span(&[(g.m, *ld)], g.n), F32, "out"),
                        a(*bos, g.n, F32, "bos"),
                        a(*h, span(&[(g.m, *h_ss)], g.n), F32, "h"),
                        a(*pos, 1, I32, "pos"),
                    ]),
                }
                v
            }
            Op::Gemm(g) => vec![
                a(g.a, span(&[(g.rows, g.lda)], g.k), W, "a"),
                a(g.w, g.n * g.k, W, "w"),
                a(
                    g.c,
                    span(&[(g.rows, g.ldc)], g.n),
                    if g.accumulate { F32 } else { EITHER },
                    "c",
                ),
            ],
            Op::AttendRows(t) => {
                let keys = match t.keys {
                    Keys::Fixed(n) => n,
                    Keys::Pos(_) => t.key_cap,
                };
                let kv = span(&[(t.batches, t.k_sb), (t.heads, t.k_sh), (keys, t.k_sj)], t.dh);
                let queries = t.batches * t.rows * t.heads;
                let mut v = vec![
                    a(
                        t.q,
                        span(&[(t.batches, t.q_sb), (t.rows, t.q_sr), (t.heads, t.dh)], t.dh),
                        F32,
                        "q",
                    ),
                    a(t.k, kv, W, "k"),
                    a(t.v, kv, W, "v"),
                    a(
                        t.y,
                        span(&[(t.batches, t.y_sb), (t.rows, t.y_sr), (t.heads, t.dh)], t.dh),
                        F32,
                        "y",
                    ),
                    a(t.part, queries * t.splits * (2 + t.dh), F32, "part"),
                    a(t.count, queries, U32, "count"),
                ];
                if let Keys::Pos(p) = t.keys {
                    v.push(a(p, 1, I32, "pos"));
                }
                v
            }
            Op::AttendTiles(t) => {
                let kv = tiles_span(&t.ks, t.instances, t.inner, t.lk, t.heads, t.dh);
                vec![
                    a(
                        t.q,
                        tiles_span(&t.qs, t.instances, t.inner, t.lq, t.heads, t.dh),
                        W,
                        "q",
                    ),
                    a(t.k, kv, W, "k"),
                    a(t.v, kv, W, "v"),
                    a(
                        t.y,
                        tiles_span(&t.ys, t.instances, t.inner, t.lq, t.heads, t.dh),
                        W,
                        "y",
                    ),
                ]
            }
            Op::Flash(f) => {
                let each = |s: &[usize; 3], rows: usize| {
                    span(&[(f.batch, s[0]), (f.heads, s[1]), (rows, s[2])], f.dh)
                };
                vec![
                    a(f.q, each(&f.qs, f.lq), W, "q"),
                    a(f.k, each(&f.ks, f.lk), W, "k"),
                    a(f.v, each(&f.vs, f.lk), W, "v"),
                    a(f.y, each(&f.ys, f.lq), W, "y"),
                    a(f.lse, f.batch * f.heads * f.lq, F32, "lse"),
                ]
            }
            Op::Rows(r) => {
                let outer = r.rows.div_ceil(r.inner.max(1));
                let src_outer = if r.period > 0 { outer.min(r.period) } else { outer };
                let mut v = vec![
                    a(
                        r.dst,
                        span(&[(outer, r.dst_s1), (r.inner.min(r.rows), r.dst_s2)], r.d),
                        if r.add { F32 } else { EITHER },
                        "dst",
                    ),
                    match r.idx {
                        // The rows an index list names are checked by the caller that wrote it.
                        Some(idx) => a(idx, r.inner, I32, "idx"),
                        None => a(
                            r.src,
                            span(&[(src_outer, r.src_s1), (r.inner.min(r.rows), r.src_s2)], r.d),
                            F32,
                            "src",
                        ),
                    },
                ];
                if let Some((g, b)) = r.norm {
                    v.extend([a(g, r.d, F32, "norm scale"), a(b, r.d, F32, "norm shift")]);
                }
                if let Some(b) = r.bias {
                    v.push(a(b, r.d, F32, "bias"));
                }
                v
            }
            Op::BiasT(b) => vec![
                a(b.x, span(&[(b.rows, b.ld)], b.cols), W, "x"),
                a(b.bias, b.cols, F32, "bias"),
            ],
            Op::Embed(e) => {
                let positions = e.p0 + e.period.min(e.rows);
                vec![
                    a(e.table, e.e, F32, "table"),
                    a(e.row_base, 1, I32, "row_base"),
                    a(e.seg_of, positions, I32, "seg_of"),
                    a(e.tok, e.rows, I32, "tok"),
                    a(e.pos_emb, positions * e.e, F32, "pos_emb"),
                    a(e.out, e.rows * e.e, W, "out"),
                ]
            }
            Op::Shift(s) => vec![
                a(s.x, s.m * s.w * s.n * s.d, F32, "x"),
                a(s.fresh, s.m * s.len * s.d, F32, "fresh"),
            ],
            Op::Align(al) => {
                let cells = al.rows * al.cols;
                vec![
                    a(al.x, al.frames * al.n * al.d, F32, "x"),
                    a(al.src, al.frames * cells * al.d, F32, "src"),
                    a(al.act, al.frames * 3, F32, "act"),
                    a(al.base, cells * 2, F32, "base"),
                ]
            }
            Op::Track(t) => vec![
                a(t.tok, t.frames * t.n, I32, "tok"),
                a(t.act, t.frames * 3, F32, "act"),
                a(t.out, t.frames * t.slots * t.k, I32, "out"),
            ],
            Op::Draw(d) => vec![
                a(d.logits, d.m * d.vocab, F32, "logits"),
                a(d.keep_logits, d.m * d.keep_cap, F32, "keep_logits"),
                a(d.rules, d.n, &[Elem::Rule], "rules"),
                a(d.runs, d.run_count, &[Elem::Run], "runs"),
                a(d.keep_on, d.m * d.keeps, U8, "keep_on"),
                a(d.newborn, d.m * d.groups, U8, "newborn"),
                a(d.tok, d.m * d.n, I32, "tok"),
                a(d.pos, 1, I32, "pos"),
                a(d.done, 1, U32, "done"),
                a(d.counts, 2, U32, "counts"),
                a(d.boxes, d.m * d.box_cap * BOX_WORDS, &[Elem::F64], "boxes"),
                a(d.nboxes, d.m, I32, "nboxes"),
                a(d.state, 3, U32, "state"),
            ],
        }
    }

    /// Refuses sizes its kernel does not take.
    pub fn validate(&self) -> Result<(), ExecError> {
        let fail = |why: String| Err(invalid(self, why));
        match self {
            Op::Gemv(g) => {
                if g.m == 0 || g.m > GEMV_ROWS || g.n == 0 || g.k == 0 {
                    return fail(format!("{} rows × {} × {} (1..={GEMV_ROWS} rows)", g.m, g.n, g.k));
                }
                if let GemvOut::Qkv { heads, dh, .. } = &g.output
                    && g.n != 3 * heads * dh
                {
                    return fail(format!("{} columns for {heads} heads of {dh}", g.n));
                }
                let vector = g.k.is_multiple_of(8);
                let rows_aligned = match &g.input {
                    GemvIn::Rows { x, ld } | GemvIn::Norm { x, ld, .. } => {
                        aligned(*x) && ld.is_multiple_of(8)
                    }
                    GemvIn::Embed { table, pos_emb, .. } => aligned(*table) && aligned(*pos_emb),
                };
                if vector && !(aligned(g.w) && rows_aligned) {
                    return fail("operands of 8-wide loads must start on multiples of 8 elements".into());
                }
            }
            Op::AttendRows(t) => {
                if t.dh == 0 || t.dh > MAX_HEAD || t.batches * t.rows * t.heads == 0 {
                    return fail(format!("head size {} (1..={MAX_HEAD})", t.dh));
                }
                let keys = match t.keys {
                    Keys::Fixed(n) => n,
                    Keys::Pos(_) => t.key_cap,
                };
                if keys == 0 {
                    return fail("no keys".into());
                }
                if t.splits * ROWS_SPLIT < keys || t.splits > ROWS_MAX_SPLITS {
                    return fail(format!(
                        "{} splits of {ROWS_SPLIT} for {keys} keys (at most {ROWS_MAX_SPLITS} splits)",
                        t.splits
                    ));
                }
                let strides = [t.k_sb, t.k_sh, t.k_sj];
                if t.dh.is_multiple_of(8)
                    && !(aligned(t.k) && aligned(t.v) && strides.iter().all(|s| s.is_multiple_of(8)))
                {
                    return fail(
                        "keys and values of 8-wide loads must start on multiples of 8 elements".into(),
                    );
                }
            }
            Op::AttendTiles(t)
                if t.dh == 0
                    || t.dh > MAX_HEAD
                    || !t.dh.is_multiple_of(4)
                    || t.lq == 0
                    || t.lk == 0
                    || t.inner == 0 =>
            {
                return fail(format!("head size {} (a multiple of 4 up to {MAX_HEAD})", t.dh));
            }
            Op::Flash(f)
                if !(f.dh == 32 || f.dh == 64) || f.lq == 0 || f.lk == 0 || f.batch * f.heads == 0 =>
            {
                return fail(format!("head size {} (32 or 64), {} × {} rows", f.dh, f.lq, f.lk));
            }
            Op::Rows(r) if r.inner == 0 || r.d == 0 => return fail("no rows".into()),
            Op::Embed(e) if e.period == 0 => return fail("period 0".into()),
            Op::Draw(d) => {
                if d.m == 0 || d.run_count == 0 || d.box_cap == 0 {
                    return fail("no scenes, group runs or box room".into());
                }
                if (d.top_k == 0 || d.top_k > DRAW_KMAX) && d.top_p < 1.0 {
                    return fail(format!(
                        "top-p {} needs a top-k of 1..={DRAW_KMAX} on the device",
                        d.top_p
                    ));
                }
            }
            _ => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spans_count_the_last_element_reached() {
        assert_eq!(span(&[(3, 10)], 4), 24);
        assert_eq!(span(&[(2, 100), (3, 10)], 4), 124);
        assert_eq!(span(&[(0, 10)], 4), 0);
        let s = Strides {
            s1: 1000,
            s2: 100,
            row: 10,
        };
        // 5 instances of inner 2: outer 0..3, inner 0..2; 2 rows, 1 head of 4.
        assert_eq!(tiles_span(&s, 5, 2, 2, 1, 4), 2 * 1000 + 100 + 10 + 4);
    }
}
