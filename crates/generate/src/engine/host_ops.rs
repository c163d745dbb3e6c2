//! The host's loops for the products, the attention, the row work and the embeddings (`gemv.cu`,
//! `attend.cu`, `rows.cu`), in f32.

use super::host::{HostExec, Store};
use umgen_cuda::ops::{
    AttendRows, AttendTiles, Buf, ExecError, Flash, Gemm, Gemv, GemvIn, GemvOut, Keys, Op, Rows,
};

/// Runs a checked operation.
pub(super) fn run(x: &mut HostExec, op: &Op) -> Result<(), ExecError> {
    match op {
        Op::Gemv(g) => gemv(x, g),
        Op::Gemm(g) => gemm(x, g),
        Op::AttendRows(t) => attend_rows(x, t),
        Op::AttendTiles(t) => attend_tiles(x, t),
        Op::Flash(f) => flash(x, f),
        Op::Rows(r) => rows(x, r),
        Op::BiasT(b) => {
            let bias = x.f32s(b.bias)[..b.cols].to_vec();
            let v = x.f32s_mut(b.x);
            for r in 0..b.rows {
                for (c, bc) in bias.iter().enumerate() {
                    let e = &mut v[r * b.ld + c];
                    *e += bc;
                    if b.gelu {
                        *e = gelu(*e);
                    }
                }
            }
            Ok(())
        }
        Op::Embed(e) => {
            let (row_base, seg_of, tok) = (x.i32s(e.row_base), x.i32s(e.seg_of), x.i32s(e.tok));
            let (table, pos) = (x.f32s(e.table), x.f32s(e.pos_emb));
            let mut out = Vec::with_capacity(e.rows * e.e);
            for (r, t) in tok[..e.rows].iter().enumerate() {
                let p = e.p0 + r % e.period;
                let row = (row_base[seg_of[p] as usize] + t) as usize;
                out.extend((0..e.e).map(|c| table[row * e.e + c] + pos[p * e.e + c]));
            }
            x.f32s_mut(e.out)[..out.len()].copy_from_slice(&out);
            Ok(())
        }
        Op::Shift(_) | Op::Align(_) | Op::Track(_) => super::host_frame::run(x, op),
        Op::Draw(d) => super::host_draw::draw(x, d),
    }
}

/// GELU's exact form, as burn's CPU backend computes it.
pub(super) fn gelu(v: f32) -> f32 {
    0.5 * v * (1.0 + libm::erff(v / std::f32::consts::SQRT_2))
}

/// `Σ a[i]·b[i]` with eight running sums (what a vector unit would do; the order differs from a GPU's).
pub(super) fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

/// A row's mean and 1/σ (biased variance, ε 1e-5).
pub(super) fn stats(row: &[f32]) -> (f32, f32) {
    let k = row.len() as f32;
    let mean = row.iter().sum::<f32>() / k;
    let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / k;
    (mean, 1.0 / (var + 1e-5).sqrt())
}

fn gemv(x: &mut HostExec, g: &Gemv) -> Result<(), ExecError> {
    let (m, n, k) = (g.m, g.n, g.k);
    let pos = |b: Buf| x.i32s(b)[0] as usize;
    let inputs: Vec<Vec<f32>> = (0..m)
        .map(|s| match &g.input {
            GemvIn::Rows { x: xb, ld } => x.f32s(*xb)[s * ld..s * ld + k].to_vec(),
            GemvIn::Norm { x: xb, ld, g: gb, b } => {
                let row = &x.f32s(*xb)[s * ld..s * ld + k];
                let (mean, rstd) = stats(row);
                let (gv, bv) = (x.f32s(*gb), x.f32s(*b));
                (0..k).map(|i| (row[i] - mean) * rstd * gv[i] + bv[i]).collect()
            }
            GemvIn::Embed {
                table,
                row_base,
                seg_of,
                tok,
                ntok,
                pos_emb,
                pos: pb,
            } => {
                let p = pos(*pb);
                let q = p.saturating_sub(1);
                let seg = x.i32s(*seg_of)[q] as usize;
                let row = (x.i32s(*row_base)[seg] + x.i32s(*tok)[s * ntok + q]) as usize;
                let (t, pe) = (x.f32s(*table), x.f32s(*pos_emb));
                (0..k).map(|i| t[row * k + i] + pe[q * k + i]).collect()
            }
        })
        .collect();
    let w = x.f32s(g.w);
    let bias = g.bias.map(|b| x.f32s(b)[..n].to_vec());
    let results: Vec<Vec<f32>> = inputs
        .iter()
        .map(|row| {
            (0..n)
                .map(|j| {
                    let mut r = dot(&w[j * k..(j + 1) * k], row);
                    if let Some(b) = &bias {
                        r += b[j];
                    }
                    if g.gelu { gelu(r) } else { r }
                })
                .collect()
        })
        .collect();
    match &g.output {
        GemvOut::Store { out, ld } | GemvOut::Add { out, ld } => {
            let add = matches!(g.output, GemvOut::Add { .. });
            let o = x.f32s_mut(*out);
            for (s, r) in results.iter().enumerate() {
                for (j, v) in r.iter().enumerate() {
                    let e = &mut o[s * ld + j];
                    *e = if add { *e + v } else { *v };
                }
            }
        }
        GemvOut::Qkv {
            q,
            ld,
            k: kc,
            v: vc,
            heads,
            dh,
            cap,
            pos: pb,
        } => {
            let p = pos(*pb);
            let dm = heads * dh;
            for (s, r) in results.iter().enumerate() {
                x.f32s_mut(*q)[s * ld..s * ld + dm].copy_from_slice(&r[..dm]);
                for (cache, part) in [(*kc, &r[dm..2 * dm]), (*vc, &r[2 * dm..])] {
                    let c = x.f32s_mut(cache);
                    for (col, v) in part.iter().enumerate() {
                        let (head, e) = (col / dh, col % dh);
                        c[((s * heads + head) * cap + p) * dh + e] = *v;
                    }
                }
            }
        }
        GemvOut::Prior {
            out,
            ld,
            bos,
            h,
            h_ss,
            pos: pb,
        } => {
            let p = pos(*pb);
            let (bos, hv) = (x.f32s(*bos)[..n].to_vec(), x.f32s(*h).to_vec());
            let o = x.f32s_mut(*out);
            for (s, r) in results.iter().enumerate() {
                for j in 0..n {
                    o[s * ld + j] = (if p == 0 { bos[j] } else { r[j] }) + hv[s * h_ss + p * n + j];
                }
            }
        }
    }
    Ok(())
}

fn gemm(x: &mut HostExec, g: &Gemm) -> Result<(), ExecError> {
    let a: Vec<f32> = x.f32s(g.a)[..(g.rows.max(1) - 1) * g.lda + g.k].to_vec();
    let w = x.f32s(g.w)[..g.n * g.k].to_vec();
    let c = x.f32s_mut(g.c);
    for r in 0..g.rows {
        let row = &a[r * g.lda..r * g.lda + g.k];
        for j in 0..g.n {
            let v = dot(&w[j * g.k..(j + 1) * g.k], row);
            let e = &mut c[r * g.ldc + j];
            *e = if g.accumulate { *e + v } else { v };
        }
    }
    Ok(())
}

/// `softmax(q·kᵀ·scale)·v` of one query over keys `0..keys` of `kv(j)` → (key row, value row).
fn attend_one<'a>(
    q: &[f32],
    keys: usize,
    scale: f32,
    kv: impl Fn(usize) -> (&'a [f32], &'a [f32]),
    out: &mut [f32],
) {
    let scores: Vec<f32> = (0..keys).map(|j| dot(q, kv(j).0) * scale).collect();
    let mx = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let p: Vec<f32> = scores.iter().map(|s| (s - mx).exp()).collect();
    let sum: f32 = p.iter().sum();
    out.iter_mut().for_each(|o| *o = 0.0);
    for (j, pj) in p.iter().enumerate() {
        for (o, v) in out.iter_mut().zip(kv(j).1) {
            *o += pj * v;
        }
    }
    out.iter_mut().for_each(|o| *o /= sum);
}

fn attend_rows(x: &mut HostExec, t: &AttendRows) -> Result<(), ExecError> {
    let keys = match t.keys {
        Keys::Fixed(n) => n,
        Keys::Pos(p) => x.i32s(p)[0] as usize + 1,
    };
    let (q, k, v) = (x.f32s(t.q).to_vec(), x.f32s(t.k).to_vec(), x.f32s(t.v).to_vec());
    let y = x.f32s_mut(t.y);
    for b in 0..t.batches {
        for r in 0..t.rows {
            for h in 0..t.heads {
                let qo = b * t.q_sb + r * t.q_sr + h * t.dh;
                let base = b * t.k_sb + h * t.k_sh;
                let row = |j: usize| {
                    let o = base + j * t.k_sj;
                    (&k[o..o + t.dh], &v[o..o + t.dh])
                };
                let yo = b * t.y_sb + r * t.y_sr + h * t.dh;
                attend_one(&q[qo..qo + t.dh], keys, t.scale, row, &mut y[yo..yo + t.dh]);
            }
        }
    }
    Ok(())
}

fn attend_tiles(x: &mut HostExec, t: &AttendTiles) -> Result<(), ExecError> {
    let (q, k, v) = (x.f32s(t.q).to_vec(), x.f32s(t.k).to_vec(), x.f32s(t.v).to_vec());
    let y = x.f32s_mut(t.y);
    for inst in 0..t.instances {
        let (i1, i2) = (inst / t.inner, inst % t.inner);
        for h in 0..t.heads {
            let kb = i1 * t.ks.s1 + i2 * t.ks.s2 + h * t.dh;
            for row in 0..t.lq {
                let qo = i1 * t.qs.s1 + i2 * t.qs.s2 + row * t.qs.row + h * t.dh;
                let keys = t.causal.map_or(t.lk, |off| (row + off + 1).min(t.lk));
                let kv = |j: usize| {
                    let o = kb + j * t.ks.row;
                    (&k[o..o + t.dh], &v[o..o + t.dh])
                };
                let yo = i1 * t.ys.s1 + i2 * t.ys.s2 + row * t.ys.row + h * t.dh;
                attend_one(&q[qo..qo + t.dh], keys, t.scale, kv, &mut y[yo..yo + t.dh]);
            }
        }
    }
    Ok(())
}

/// FlashAttention-2's function (its arithmetic in f32 here): every head's rows, and their log-sum-exp.
fn flash(x: &mut HostExec, f: &Flash) -> Result<(), ExecError> {
    let (q, k, v) = (x.f32s(f.q).to_vec(), x.f32s(f.k).to_vec(), x.f32s(f.v).to_vec());
    let scale = (f.dh as f32).sqrt().recip();
    let off = f.lk.saturating_sub(f.lq);
    let mut lse = vec![0.0f32; f.batch * f.heads * f.lq];
    let y = x.f32s_mut(f.y);
    for b in 0..f.batch {
        for h in 0..f.heads {
            for row in 0..f.lq {
                let keys = if f.causal { (row + off + 1).min(f.lk) } else { f.lk };
                let qo = b * f.qs[0] + h * f.qs[1] + row * f.qs[2];
                let kv = |j: usize| {
                    let (ko, vo) = (
                        b * f.ks[0] + h * f.ks[1] + j * f.ks[2],
                        b * f.vs[0] + h * f.vs[1] + j * f.vs[2],
                    );
                    (&k[ko..ko + f.dh], &v[vo..vo + f.dh])
                };
                let yo = b * f.ys[0] + h * f.ys[1] + row * f.ys[2];
                attend_one(&q[qo..qo + f.dh], keys, scale, kv, &mut y[yo..yo + f.dh]);
                let scores: Vec<f32> = (0..keys)
                    .map(|j| dot(&q[qo..qo + f.dh], kv(j).0) * scale)
                    .collect();
                let mx = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                lse[(b * f.heads + h) * f.lq + row] =
                    mx + scores.iter().map(|s| (s - mx).exp()).sum::<f32>().ln();
            }
        }
    }
    x.f32s_mut(f.lse)[..lse.len()].copy_from_slice(&lse);
    Ok(())
}

fn rows(x: &mut HostExec, r: &Rows) -> Result<(), ExecError> {
    let idx = r.idx.map(|b| x.i32s(b)[..r.inner].to_vec());
    let norm = r
        .norm
        .map(|(g, b)| (x.f32s(g)[..r.d].to_vec(), x.f32s(b)[..r.d].to_vec()));
    let bias = r.bias.map(|b| x.f32s(b)[..r.d].to_vec());
    // The source may be the destination (a bias added in place): read every source row first.
    let src: Vec<Vec<f32>> = (0..r.rows)
        .map(|row| {
            let (mut i1, i2) = (row / r.inner, row % r.inner);
            if r.period > 0 {
                i1 %= r.period;
            }
            let j = idx.as_ref().map_or(i2, |v| v[i2] as usize);
            let o = i1 * r.src_s1 + j * r.src_s2;
            let s = &x.f32s(r.src)[o..o + r.d];
            let mut v: Vec<f32> = match &norm {
                Some((g, b)) => {
                    let (mean, rstd) = stats(s);
                    s.iter()
                        .zip(g)
                        .zip(b)
                        .map(|((v, g), b)| (v - mean) * rstd * g + b)
                        .collect()
                }
                None => s.to_vec(),
            };
            if let Some(b) = &bias {
                v.iter_mut().zip(b).for_each(|(v, b)| *v += b);
            }
            if r.gelu {
                v.iter_mut().for_each(|v| *v = gelu(*v));
            }
            v
        })
        .collect();
    let store = x.take(r.dst.id);
    let Store::F32(mut dst) = store else {
        x.put(r.dst.id, store);
        return Err(ExecError::Invalid("rows: the destination is not f32".into()));
    };
    for (row, v) in src.iter().enumerate() {
        let o = r.dst.at + (row / r.inner) * r.dst_s1 + (row % r.inner) * r.dst_s2;
        for (c, val) in v.iter().enumerate() {
            dst[o + c] = if r.add { dst[o + c] + val } else { *val };
        }
    }
    x.put(r.dst.id, Store::F32(dst));
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::panic)]
    use super::*;
    use umgen_cuda::ops::{Data, Elem, Exec, Strides};

    /// The flash operation and the tiled one compute the same attention over the same strided operands.
    #[test]
    fn flash_equals_tiled_attention_on_the_host() {
        let mut x = HostExec::new();
        let (frames, n, heads, dh) = (3, 37, 2, 8);
        let d = heads * dh;
        let qkv = x
            .alloc(Elem::W, frames * n * 3 * d)
            .unwrap_or_else(|e| panic!("{e}"));
        let values: Vec<f32> = (0..frames * n * 3 * d)
            .map(|i| ((i * 7919 % 97) as f32 - 48.0) / 31.0)
            .collect();
        x.write(qkv, Data::F32(&values)).unwrap_or_else(|e| panic!("{e}"));
        let (y1, y2) = (x.alloc(Elem::W, frames * n * d), x.alloc(Elem::W, frames * n * d));
        let (y1, y2) = (
            y1.unwrap_or_else(|e| panic!("{e}")),
            y2.unwrap_or_else(|e| panic!("{e}")),
        );
        let lse = x
            .alloc(Elem::F32, frames * heads * n)
            .unwrap_or_else(|e| panic!("{e}"));
        for causal in [false, true] {
            let qs = Strides {
                s1: n * 3 * d,
                s2: 0,
                row: 3 * d,
            };
            let tiles = Op::AttendTiles(AttendTiles {
                q: qkv,
                k: qkv.at(d),
                v: qkv.at(2 * d),
                y: y1,
                qs,
                ks: qs,
                ys: Strides {
                    s1: n * d,
                    s2: 0,
                    row: d,
                },
                instances: frames,
                inner: 1,
                heads,
                lq: n,
                lk: n,
                dh,
                causal: causal.then_some(0),
                scale: (dh as f32).sqrt().recip(),
            });
            let s3 = [n * 3 * d, dh, 3 * d];
            let flash = Op::Flash(Flash {
                q: qkv,
                k: qkv.at(d),
                v: qkv.at(2 * d),
                y: y2,
                lse,
                qs: s3,
                ks: s3,
                vs: s3,
                ys: [n * d, dh, d],
                batch: frames,
                heads,
                lq: n,
                lk: n,
                dh: 32.max(dh),
                causal,
            });
            x.run(&tiles).unwrap_or_else(|e| panic!("{e}"));
            // The flash kernels take head sizes 32 and 64: the check of the operation refuses 8.
            assert!(x.run(&flash).is_err());
            let Op::Flash(mut f) = flash else {
                panic!("a flash operation")
            };
            f.dh = dh;
            flash_unchecked(&mut x, &f);
            let (a, b) = (x.read_f32(y1, frames * n * d), x.read_f32(y2, frames * n * d));
            let (a, b) = (
                a.unwrap_or_else(|e| panic!("{e}")),
                b.unwrap_or_else(|e| panic!("{e}")),
            );
            let err = a
                .iter()
                .zip(&b)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0f32, f32::max);
            assert!(err < 1e-5, "causal {causal}: {err}");
        }
    }

    fn flash_unchecked(x: &mut HostExec, f: &Flash) {
        flash(x, f).unwrap_or_else(|e| panic!("{e}"));
    }
}
