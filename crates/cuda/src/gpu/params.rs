//! The kernels' parameter structs, field for field as `src/kernels/*.cu` declares them (pointers as
//! device addresses), built from an operation's arguments.

use super::CudaExec;
use crate::ops::{self, GemvIn, GemvOut, GroupRun, Keys, Rule};
use cudarc::driver::DeviceRepr;

/// `struct Gemv` of `gemv.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Gemv {
    w: u64,
    x: u64,
    g: u64,
    b: u64,
    table: u64,
    row_base: u64,
    seg_of: u64,
    tok: u64,
    pos_emb: u64,
    pos: u64,
    bias: u64,
    out: u64,
    kc: u64,
    vc: u64,
    bos: u64,
    h: u64,
    h_ss: i64,
    m: i32,
    n: i32,
    k: i32,
    ldx: i32,
    ldo: i32,
    ntok: i32,
    in_mode: i32,
    gelu: i32,
    out_mode: i32,
    heads: i32,
    dh: i32,
    cap: i32,
}

/// `struct AttendRows` of `attend.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct AttendRows {
    q: u64,
    k: u64,
    v: u64,
    y: u64,
    pos: u64,
    part: u64,
    count: u64,
    q_sb: i64,
    q_sr: i64,
    k_sb: i64,
    k_sh: i64,
    k_sj: i64,
    y_sb: i64,
    y_sr: i64,
    rows: i32,
    heads: i32,
    dh: i32,
    lk: i32,
    splits: i32,
    scale: f32,
}

/// `struct AttendTiles` of `attend.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct AttendTiles {
    q: u64,
    k: u64,
    v: u64,
    y: u64,
    strides: [i64; 9],
    inner: i32,
    heads: i32,
    lq: i32,
    lk: i32,
    dh: i32,
    causal: i32,
    off: i32,
    scale: f32,
}

/// `struct Params` of `flash2/flash2_tiles.cu`: pointers as device addresses, each stride triple (batch,
/// head, row) in elements. The engine's window pass and the backbone's training attention both launch
/// flash2 with it.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct Flash2 {
    /// Queries, keys and values (forward and backward).
    pub q: u64,
    /// Keys.
    pub k: u64,
    /// Values.
    pub v: u64,
    /// The output's gradient (backward).
    pub dout: u64,
    /// The forward pass's log-sum-exp rows (backward).
    pub lse: u64,
    /// Rows of `dout · out` (backward).
    pub delta: u64,
    /// The output (forward).
    pub out: u64,
    /// The log-sum-exp rows written (forward).
    pub lse_out: u64,
    /// The queries' gradient (backward).
    pub dq: u64,
    /// The keys' gradient (backward).
    pub dk: u64,
    /// The values' gradient (backward).
    pub dv: u64,
    /// Strides of `q`.
    pub qs: [i64; 3],
    /// Strides of `k`.
    pub ks: [i64; 3],
    /// Strides of `v`.
    pub vs: [i64; 3],
    /// Strides of `dout`.
    pub os: [i64; 3],
    /// Strides of `lse`.
    pub ls: [i64; 3],
    /// Strides of `delta`.
    pub es: [i64; 3],
    /// Strides of `out`.
    pub outs: [i64; 3],
    /// Strides of `dq`.
    pub dqs: [i64; 3],
    /// Strides of `dk`.
    pub dks: [i64; 3],
    /// Strides of `dv`.
    pub dvs: [i64; 3],
    /// Heads per batch entry.
    pub heads: i32,
    /// Query rows.
    pub lq: i32,
    /// Key rows.
    pub lk: i32,
    /// Causal offset: key `j` is hidden from query `i` when `j > i + off`.
    pub off: i32,
    /// 1 for causal attention.
    pub causal: i32,
    /// The scores' scale, 1/√d.
    pub scale: f32,
    /// Batch entries × heads.
    pub count: i32,
}

/// `struct Rows` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Rows {
    src: u64,
    idx: u64,
    dst: u64,
    g: u64,
    b: u64,
    bias: u64,
    s_s1: i64,
    s_s2: i64,
    d_s1: i64,
    d_s2: i64,
    rows: i32,
    inner: i32,
    period: i32,
    d: i32,
    add: i32,
    gelu: i32,
}

/// `struct BiasT` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct BiasT {
    x: u64,
    bias: u64,
    rows: i64,
    cols: i32,
    ld: i32,
    gelu: i32,
}

/// `struct Embed` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Embed {
    table: u64,
    row_base: u64,
    seg_of: u64,
    tok: u64,
    pos_emb: u64,
    out: u64,
    rows: i64,
    period: i32,
    p0: i32,
    e: i32,
}

/// `struct Shift` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Shift {
    x: u64,
    fresh: u64,
    m: i32,
    w: i32,
    n: i32,
    d: i32,
    start: i32,
    len: i32,
}

/// `struct Align` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Align {
    x: u64,
    src: u64,
    act: u64,
    base: u64,
    frames: i32,
    n: i32,
    d: i32,
    offset: i32,
    rows: i32,
    cols: i32,
    tx_scale: f32,
    ty_scale: f32,
}

/// `struct Track` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Track {
    tok: u64,
    act: u64,
    out: u64,
    frames: i32,
    w: i32,
    n: i32,
    offset: i32,
    slots: i32,
    k: i32,
    values: i32,
    pad: i32,
    accel: i32,
    field: [i32; 5],
    bins: [i32; 5],
    lo: [f32; 5],
    hi: [f32; 5],
    width: [f32; 5],
    step: f32,
}

/// `struct Draw` of `draw.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(super) struct Draw {
    logits: u64,
    keep_logits: u64,
    rules: u64,
    runs: u64,
    keep_on: u64,
    newborn: u64,
    tok: u64,
    pos: u64,
    done: u64,
    counts: u64,
    boxes: u64,
    nboxes: u64,
    state: u64,
    temperature: f64,
    top_p: f64,
    m: i32,
    n: i32,
    vocab: i32,
    top_k: i32,
    keeps: i32,
    groups: i32,
    box_cap: i32,
    key0: u32,
    key1: u32,
}

// SAFETY: plain `#[repr(C)]` structs of integers and floats, laid out as the kernels' structs.
unsafe impl DeviceRepr for Gemv {}
// SAFETY: as above.
unsafe impl DeviceRepr for AttendRows {}
// SAFETY: as above.
unsafe impl DeviceRepr for AttendTiles {}
// SAFETY: as above.
unsafe impl DeviceRepr for Flash2 {}
// SAFETY: as above.
unsafe impl DeviceRepr for Rows {}
// SAFETY: as above.
unsafe impl DeviceRepr for BiasT {}
// SAFETY: as above.
unsafe impl DeviceRepr for Embed {}
// SAFETY: as above.
unsafe impl DeviceRepr for Shift {}
// SAFETY: as above.
unsafe impl DeviceRepr for Align {}
// SAFETY: as above.
unsafe impl DeviceRepr for Track {}
// SAFETY: as above.
unsafe impl DeviceRepr for Draw {}

/// Sizes fit the kernels' `int`s (checked where the engine sizes its buffers; saturate rather than wrap).
fn i(x: usize) -> i32 {
    i32::try_from(x).unwrap_or(i32::MAX)
}

fn l(x: usize) -> i64 {
    i64::try_from(x).unwrap_or(i64::MAX)
}

impl CudaExec {
    fn opt(&self, b: Option<ops::Buf>) -> u64 {
        b.map_or(0, |b| self.ptr(b))
    }

    pub(super) fn gemv(&self, g: &ops::Gemv) -> Gemv {
        let mut p = Gemv {
            w: self.ptr(g.w),
            bias: self.opt(g.bias),
            m: i(g.m),
            n: i(g.n),
            k: i(g.k),
            gelu: i32::from(g.gelu),
            ..Default::default()
        };
        match &g.input {
            GemvIn::Rows { x, ld } => (p.x, p.ldx, p.in_mode) = (self.ptr(*x), i(*ld), 0),
            GemvIn::Norm { x, ld, g: s, b } => {
                (p.x, p.ldx, p.in_mode) = (self.ptr(*x), i(*ld), 1);
                (p.g, p.b) = (self.ptr(*s), self.ptr(*b));
            }
            GemvIn::Embed {
                table,
                row_base,
                seg_of,
                tok,
                ntok,
                pos_emb,
                pos,
            } => {
                p.in_mode = 2;
                (p.table, p.row_base, p.seg_of) = (self.ptr(*table), self.ptr(*row_base), self.ptr(*seg_of));
                (p.tok, p.ntok, p.pos_emb, p.pos) =
                    (self.ptr(*tok), i(*ntok), self.ptr(*pos_emb), self.ptr(*pos));
            }
        }
        match &g.output {
            GemvOut::Store { out, ld } => (p.out, p.ldo, p.out_mode) = (self.ptr(*out), i(*ld), 0),
            GemvOut::Add { out, ld } => (p.out, p.ldo, p.out_mode) = (self.ptr(*out), i(*ld), 1),
            GemvOut::Qkv {
                q,
                ld,
                k,
                v,
                heads,
                dh,
                cap,
                pos,
            } => {
                (p.out, p.ldo, p.out_mode) = (self.ptr(*q), i(*ld), 2);
                (p.kc, p.vc, p.pos) = (self.ptr(*k), self.ptr(*v), self.ptr(*pos));
                (p.heads, p.dh, p.cap) = (i(*heads), i(*dh), i(*cap));
            }
            GemvOut::Prior {
                out,
                ld,
                bos,
                h,
                h_ss,
                pos,
            } => {
                (p.out, p.ldo, p.out_mode) = (self.ptr(*out), i(*ld), 3);
                (p.bos, p.h, p.h_ss, p.pos) = (self.ptr(*bos), self.ptr(*h), l(*h_ss), self.ptr(*pos));
            }
        }
        p
    }

    pub(super) fn attend_rows(&self, t: &ops::AttendRows) -> AttendRows {
        let (pos, lk) = match t.keys {
            Keys::Fixed(n) => (0, n),
            Keys::Pos(b) => (self.ptr(b), 0),
        };
        AttendRows {
            q: self.ptr(t.q),
            k: self.ptr(t.k),
            v: self.ptr(t.v),
            y: self.ptr(t.y),
            pos,
            part: self.ptr(t.part),
            count: self.ptr(t.count),
            q_sb: l(t.q_sb),
            q_sr: l(t.q_sr),
            k_sb: l(t.k_sb),
            k_sh: l(t.k_sh),
            k_sj: l(t.k_sj),
            y_sb: l(t.y_sb),
            y_sr: l(t.y_sr),
            rows: i(t.rows),
            heads: i(t.heads),
            dh: i(t.dh),
            lk: i(lk),
            splits: i(t.splits),
            scale: t.scale,
        }
    }

    pub(super) fn attend_tiles(&self, t: &ops::AttendTiles) -> AttendTiles {
        let s = [t.qs, t.ks, t.ys];
        AttendTiles {
            q: self.ptr(t.q),
            k: self.ptr(t.k),
            v: self.ptr(t.v),
            y: self.ptr(t.y),
            strides: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|j| {
                let st = s[j / 3];
                l([st.s1, st.s2, st.row][j % 3])
            }),
            inner: i(t.inner),
            heads: i(t.heads),
            lq: i(t.lq),
            lk: i(t.lk),
            dh: i(t.dh),
            causal: i32::from(t.causal.is_some()),
            off: i(t.causal.unwrap_or(0)),
            scale: t.scale,
        }
    }

    pub(super) fn flash2(&self, f: &ops::Flash) -> Flash2 {
        let st = |s: &[usize; 3]| s.map(l);
        Flash2 {
            q: self.ptr(f.q),
            k: self.ptr(f.k),
            v: self.ptr(f.v),
            out: self.ptr(f.y),
            lse_out: self.ptr(f.lse),
            qs: st(&f.qs),
            ks: st(&f.ks),
            vs: st(&f.vs),
            outs: st(&f.ys),
            heads: i(f.heads),
            lq: i(f.lq),
            lk: i(f.lk),
            off: i(f.lk.saturating_sub(f.lq)),
            causal: i32::from(f.causal),
            scale: (f.dh as f32).sqrt().recip(),
            count: i(f.batch * f.heads),
            ..Default::default()
        }
    }

    pub(super) fn rows(&self, r: &ops::Rows) -> Rows {
        let (g, b) = r.norm.map_or((0, 0), |(g, b)| (self.ptr(g), self.ptr(b)));
        Rows {
            src: self.ptr(r.src),
            idx: self.opt(r.idx),
            dst: self.ptr(r.dst),
            g,
            b,
            bias: self.opt(r.bias),
            s_s1: l(r.src_s1),
            s_s2: l(r.src_s2),
            d_s1: l(r.dst_s1),
            d_s2: l(r.dst_s2),
            rows: i(r.rows),
            inner: i(r.inner),
            period: i(r.period),
            d: i(r.d),
            add: i32::from(r.add),
            gelu: i32::from(r.gelu),
        }
    }

    pub(super) fn bias_t(&self, b: &ops::BiasT) -> BiasT {
        BiasT {
            x: self.ptr(b.x),
            bias: self.ptr(b.bias),
            rows: l(b.rows),
            cols: i(b.cols),
            ld: i(b.ld),
            gelu: i32::from(b.gelu),
        }
    }

    pub(super) fn embed(&self, e: &ops::Embed) -> Embed {
        Embed {
            table: self.ptr(e.table),
            row_base: self.ptr(e.row_base),
            seg_of: self.ptr(e.seg_of),
            tok: self.ptr(e.tok),
            pos_emb: self.ptr(e.pos_emb),
            out: self.ptr(e.out),
            rows: l(e.rows),
            period: i(e.period),
            p0: i(e.p0),
            e: i(e.e),
        }
    }

    pub(super) fn shift(&self, s: &ops::Shift) -> Shift {
        Shift {
            x: self.ptr(s.x),
            fresh: self.ptr(s.fresh),
            m: i(s.m),
            w: i(s.w),
            n: i(s.n),
            d: i(s.d),
            start: i(s.start),
            len: i(s.len),
        }
    }

    pub(super) fn align(&self, a: &ops::Align) -> Align {
        Align {
            x: self.ptr(a.x),
            src: self.ptr(a.src),
            act: self.ptr(a.act),
            base: self.ptr(a.base),
            frames: i(a.frames),
            n: i(a.n),
            d: i(a.d),
            offset: i(a.offset),
            rows: i(a.rows),
            cols: i(a.cols),
            tx_scale: a.tx_scale,
            ty_scale: a.ty_scale,
        }
    }

    pub(super) fn track(&self, t: &ops::Track) -> Track {
        let f = &t.fields;
        Track {
            tok: self.ptr(t.tok),
            act: self.ptr(t.act),
            out: self.ptr(t.out),
            frames: i(t.frames),
            w: i(t.w),
            n: i(t.n),
            offset: i(t.offset),
            slots: i(t.slots),
            k: i(t.k),
            values: i(t.values as usize),
            pad: t.pad.map_or(-1, |p| i(p as usize)),
            accel: i32::from(t.accel),
            field: f.map(|x| i(x.index)),
            bins: f.map(|x| i(x.bins as usize)),
            lo: f.map(|x| x.lo),
            hi: f.map(|x| x.hi),
            width: f.map(|x| x.width),
            step: t.step,
        }
    }

    pub(super) fn draw(&self, d: &ops::Draw) -> Draw {
        Draw {
            logits: self.ptr(d.logits),
            keep_logits: self.ptr(d.keep_logits),
            rules: self.ptr(d.rules),
            runs: self.ptr(d.runs),
            keep_on: self.ptr(d.keep_on),
            newborn: self.ptr(d.newborn),
            tok: self.ptr(d.tok),
            pos: self.ptr(d.pos),
            done: self.ptr(d.done),
            counts: self.ptr(d.counts),
            boxes: self.ptr(d.boxes),
            nboxes: self.ptr(d.nboxes),
            state: self.ptr(d.state),
            temperature: d.temperature,
            top_p: d.top_p,
            m: i(d.m),
            n: i(d.n),
            vocab: i(d.vocab),
            top_k: i(d.top_k),
            keeps: i(d.keeps),
            groups: i(d.groups),
            box_cap: i(d.box_cap),
            key0: d.key[0],
            key1: d.key[1],
        }
    }
}

/// A rule's bytes as `draw.cu` reads them.
pub(super) fn rule_bytes(r: &Rule) -> Vec<u8> {
    [
        r.known, r.limit, r.gstart, r.gj, r.grun, r.gindex, r.finish, r.keep, r.keep_pad, r.keep_off,
    ]
    .iter()
    .flat_map(|x| x.to_le_bytes())
    .collect()
}

/// A group run's bytes as `draw.cu` reads them (four bytes of padding before the doubles).
pub(super) fn run_bytes(g: &GroupRun) -> Vec<u8> {
    let ints = [
        g.size,
        g.pad,
        g.values,
        g.last_lo,
        g.last_hi,
        g.boxes,
        g.max_boxes,
    ];
    let mut out: Vec<u8> = ints
        .iter()
        .chain(&g.field)
        .chain(&g.bins)
        .flat_map(|x| x.to_le_bytes())
        .collect();
    out.extend([0u8; 4]);
    out.extend(g.lo.iter().chain(&g.hi).flat_map(|x| x.to_le_bytes()));
    debug_assert_eq!(out.len(), size_of::<GroupRun>());
    out
}
