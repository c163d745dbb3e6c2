//! The kernels' parameter structs, field for field as `src/kernels/*.cu` declares them (pointers as
//! device addresses), built from an operation's arguments: the decoding step's products and attentions
//! and flash2 here, the window pass's row operations and the draw in [`frame`].

mod frame;

pub(super) use frame::{rule_bytes, run_bytes};

use super::exec::CudaExec;
use crate::ops::{self, GemvIn, GemvOut, Keys};
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
    /// The one-pass backward pass's f32 accumulator of `dq`, `[count, lq, 64]` contiguous.
    pub dq_acc: u64,
}

// SAFETY: a plain `#[repr(C)]` struct of integers and floats, laid out as the kernel's struct.
unsafe impl DeviceRepr for Gemv {}
// SAFETY: as above.
unsafe impl DeviceRepr for AttendRows {}
// SAFETY: as above.
unsafe impl DeviceRepr for AttendTiles {}
// SAFETY: as above.
unsafe impl DeviceRepr for Flash2 {}

/// Sizes fit the kernels' `int`s (checked where the engine sizes its buffers; saturate rather than wrap).
pub(in crate::gpu) fn i(x: usize) -> i32 {
    i32::try_from(x).unwrap_or(i32::MAX)
}

pub(in crate::gpu) fn l(x: usize) -> i64 {
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
}
