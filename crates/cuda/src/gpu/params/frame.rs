//! Parameter structs of the window pass's row operations (`rows.cu`) and of the draw (`draw.cu`), with the
//! byte layouts of the draw's rule and group-run tables.

use super::{i, l};
use crate::gpu::exec::CudaExec;
use crate::ops::{self, GroupRun, Rule};
use cudarc::driver::DeviceRepr;

/// `struct Rows` of `rows.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(in crate::gpu) struct Rows {
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
pub(in crate::gpu) struct BiasT {
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
pub(in crate::gpu) struct Embed {
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
pub(in crate::gpu) struct Shift {
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
pub(in crate::gpu) struct Align {
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
pub(in crate::gpu) struct Track {
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
    /// Whether `follow_rule` applies: half width, cos heading, min gap, min room, onset, max.
    follow: i32,
    follow_rule: [f32; 6],
    /// Stop slots the follow rule brakes for (0: none), then their segment's offset, tokens per slot,
    /// value ids, state position, x/y/heading positions, stop and go ids (−1: unused), bins and gap.
    stops: i32,
    stop_offset: i32,
    stop_k: i32,
    stop_values: i32,
    stop_state: i32,
    stop_field: [i32; 3],
    stop_ids: [i32; 4],
    go_ids: [i32; 4],
    stop_lo: [f32; 3],
    stop_width: [f32; 3],
    stop_gap: f32,
}

/// `struct Draw` of `draw.cu`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub(in crate::gpu) struct Draw {
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
    top_p_rest: i32,
}

// SAFETY: a plain `#[repr(C)]` struct of integers and floats, laid out as the kernel's struct.
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

impl CudaExec {
    pub(in crate::gpu) fn rows(&self, r: &ops::Rows) -> Rows {
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

    pub(in crate::gpu) fn bias_t(&self, b: &ops::BiasT) -> BiasT {
        BiasT {
            x: self.ptr(b.x),
            bias: self.ptr(b.bias),
            rows: l(b.rows),
            cols: i(b.cols),
            ld: i(b.ld),
            gelu: i32::from(b.gelu),
        }
    }

    pub(in crate::gpu) fn embed(&self, e: &ops::Embed) -> Embed {
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

    pub(in crate::gpu) fn shift(&self, s: &ops::Shift) -> Shift {
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

    pub(in crate::gpu) fn align(&self, a: &ops::Align) -> Align {
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

    pub(in crate::gpu) fn track(&self, t: &ops::Track) -> Track {
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
            follow: i32::from(t.follow.is_some()),
            follow_rule: t.follow.map_or([0.0; 6], |r| {
                [r.half_width, r.cos_heading, r.min_gap, r.min_room, r.onset, r.max]
            }),
            stops: t.stops.map_or(0, |st| i(st.slots)),
            stop_offset: t.stops.map_or(0, |st| i(st.offset)),
            stop_k: t.stops.map_or(0, |st| i(st.k)),
            stop_values: t.stops.map_or(0, |st| i(st.values as usize)),
            stop_state: t.stops.map_or(0, |st| i(st.state)),
            stop_field: t.stops.map_or([0; 3], |st| st.fields.map(|x| i(x.index))),
            stop_ids: t.stops.map_or([-1; 4], |st| st.stop),
            go_ids: t.stops.map_or([-1; 4], |st| st.go),
            stop_lo: t.stops.map_or([0.0; 3], |st| st.fields.map(|x| x.lo)),
            stop_width: t.stops.map_or([0.0; 3], |st| st.fields.map(|x| x.width)),
            stop_gap: t.stops.map_or(0.0, |st| st.gap),
        }
    }

    pub(in crate::gpu) fn draw(&self, d: &ops::Draw) -> Draw {
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
            top_p_rest: i32::from(d.top_p_rest),
        }
    }
}

/// A rule's bytes as `draw.cu` reads them.
pub(in crate::gpu) fn rule_bytes(r: &Rule) -> Vec<u8> {
    [
        r.known, r.limit, r.gstart, r.gj, r.grun, r.gindex, r.finish, r.keep, r.keep_pad, r.keep_off,
    ]
    .iter()
    .flat_map(|x| x.to_le_bytes())
    .collect()
}

/// A group run's bytes as `draw.cu` reads them (four bytes of padding before the doubles).
pub(in crate::gpu) fn run_bytes(g: &GroupRun) -> Vec<u8> {
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
