//! The model's weights in an executor's buffers: every linear layer's weights transposed to `[d_out][d_in]`
//! rows in the weights' type (`W`: bf16 or f32), which the matrix-vector kernel reads a row per output and
//! cuBLAS takes transposed; biases, norms, tables and embeddings in f32. Codebook tables are projected to
//! the embedding width once, here.

use crate::error::{GenerateError, Result};
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use umgen_backbone::{PlainBackbone, PlainCross, PlainLinear, PlainNorm, PlainSelf};
use umgen_cuda::ops::{Buf, Data, Elem, Exec};

/// A linear layer: `w` `[n][k]` (`W`), an optional bias `[n]`.
#[derive(Debug, Clone, Copy)]
pub(super) struct LinearW {
    pub(super) w: Buf,
    pub(super) b: Option<Buf>,
    pub(super) n: usize,
    pub(super) k: usize,
}

/// A layer norm's scale and shift.
#[derive(Debug, Clone, Copy)]
pub(super) struct NormW {
    pub(super) g: Buf,
    pub(super) b: Buf,
}

/// A self-attention layer, its q and kv projections as one `[3d][d]` product.
#[derive(Debug, Clone, Copy)]
pub(super) struct SelfW {
    pub(super) ln1: NormW,
    pub(super) qkv: LinearW,
    pub(super) proj: LinearW,
    pub(super) ln2: NormW,
    pub(super) fc: LinearW,
    pub(super) fc2: LinearW,
}

/// A cross-attention layer.
#[derive(Debug, Clone, Copy)]
pub(super) struct CrossW {
    pub(super) ln_q: NormW,
    pub(super) ln_ctx: NormW,
    pub(super) q: LinearW,
    pub(super) kv: LinearW,
    pub(super) proj: LinearW,
    pub(super) ln2: NormW,
    pub(super) fc: LinearW,
    pub(super) fc2: LinearW,
}

/// The ego module.
#[derive(Debug, Clone)]
pub(super) struct EgoW {
    pub(super) queries: Buf,
    pub(super) q: usize,
    pub(super) hist: Vec<CrossW>,
    pub(super) env: Vec<CrossW>,
    pub(super) ln: NormW,
    pub(super) head: LinearW,
    pub(super) block: [usize; 2],
    pub(super) last: Option<usize>,
}

/// Every weight of the model.
#[derive(Debug, Clone)]
pub(super) struct Weights {
    /// Every segment's table rows, projected to the embedding width `[Σ embed_vocab][e]`.
    pub(super) table: Buf,
    /// Each segment's first row in `table` (i32).
    pub(super) row_base: Buf,
    /// Each frame position's segment (i32).
    pub(super) seg_of: Buf,
    pub(super) pos_emb: Buf,
    pub(super) fc1: LinearW,
    pub(super) fc2: LinearW,
    pub(super) time: Buf,
    pub(super) ego: Option<EgoW>,
    pub(super) tar: Vec<(SelfW, SelfW)>,
    pub(super) ln_tar: NormW,
    pub(super) bos: Buf,
    pub(super) oar: Vec<SelfW>,
    pub(super) ln_oar: NormW,
    pub(super) track: Option<(LinearW, LinearW)>,
    pub(super) tar_heads: Vec<LinearW>,
    pub(super) oar_heads: Vec<LinearW>,
}

/// `a` `[rows][cols]` row-major, transposed, in tiles (a plain double loop thrashes the cache on the
/// paper's 768 × 3,072 layers).
pub(super) fn transpose(a: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    const TILE: usize = 64;
    let mut out = vec![0.0; a.len()];
    for r0 in (0..rows).step_by(TILE) {
        for c0 in (0..cols).step_by(TILE) {
            for r in r0..(r0 + TILE).min(rows) {
                for c in c0..(c0 + TILE).min(cols) {
                    out[c * rows + r] = a[r * cols + c];
                }
            }
        }
    }
    out
}

/// Uploads `data` into a new buffer of `elem`.
pub(super) fn upload<X: Exec>(x: &mut X, elem: Elem, data: &[f32]) -> Result<Buf> {
    let b = x.alloc(elem, data.len())?;
    x.write(b, Data::F32(data))?;
    Ok(b)
}

fn upload_i32<X: Exec>(x: &mut X, data: &[i32]) -> Result<Buf> {
    let b = x.alloc(Elem::I32, data.len())?;
    x.write(b, Data::I32(data))?;
    Ok(b)
}

/// A linear layer laid out for the executor: `w` `[n][k]`, the bias `[n]` if any.
struct HostLinear {
    w: Vec<f32>,
    b: Option<Vec<f32>>,
    n: usize,
    k: usize,
}

/// Layers whose outputs are stacked: `[Σ n][k]` weights and their biases (zeros where a layer has none).
fn host_linear(parts: &[&PlainLinear]) -> Result<HostLinear> {
    let k = parts.first().map_or(0, |p| p.d_in);
    if parts.iter().any(|p| p.d_in != k) {
        return Err(GenerateError::Settings(
            "stacked layers of different input widths".into(),
        ));
    }
    let n: usize = parts.iter().map(|p| p.d_out).sum();
    let mut w = Vec::with_capacity(n * k);
    let mut b = Vec::with_capacity(n);
    for p in parts {
        w.extend(transpose(&p.w, p.d_in, p.d_out));
        b.extend(p.b.clone().unwrap_or_else(|| vec![0.0; p.d_out]));
    }
    let has_bias = parts.iter().any(|p| p.b.is_some());
    Ok(HostLinear {
        w,
        b: has_bias.then_some(b),
        n,
        k,
    })
}

/// The host layouts of a model's linear layers, made on several threads before the uploads (a plain loop
/// spent seconds on the `paper` sizes' transposes), by the address of each group's first layer.
/// The second field counts groups laid out on the uploading thread because [`groups`] missed them.
struct Prepared(HashMap<usize, Result<HostLinear>>, usize);

impl Prepared {
    /// Every group of `groups` laid out, on up to 16 threads.
    fn of(groups: &[Vec<&PlainLinear>]) -> Self {
        let next = AtomicUsize::new(0);
        let threads = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .clamp(1, 16);
        let done: Vec<Vec<(usize, Result<HostLinear>)>> = std::thread::scope(|s| {
            let workers: Vec<_> = (0..threads)
                .map(|_| {
                    s.spawn(|| {
                        let mut mine = Vec::new();
                        loop {
                            let i = next.fetch_add(1, Ordering::Relaxed);
                            let Some(g) = groups.get(i) else { break };
                            mine.push((key(g), host_linear(g)));
                        }
                        mine
                    })
                })
                .collect();
            // A worker that panicked leaves its groups to `stacked`, which lays them out itself.
            workers.into_iter().filter_map(|w| w.join().ok()).collect()
        });
        Self(done.into_iter().flatten().collect(), 0)
    }

    /// `parts` laid out: prepared, or made now (counted: [`groups`] should have listed it).
    fn take(&mut self, parts: &[&PlainLinear]) -> Result<HostLinear> {
        self.0.remove(&key(parts)).unwrap_or_else(|| {
            self.1 += 1;
            host_linear(parts)
        })
    }
}

/// A group's key: the address of its first layer.
fn key(parts: &[&PlainLinear]) -> usize {
    parts
        .first()
        .map_or(0, |p| std::ptr::from_ref::<PlainLinear>(p) as usize)
}

/// Every group of linear layers [`Weights::upload`] stacks, in the order it uploads them.
fn groups(m: &PlainBackbone) -> Vec<Vec<&PlainLinear>> {
    let mut g: Vec<Vec<&PlainLinear>> = vec![vec![&m.embed.fc1], vec![&m.embed.fc2]];
    if let Some(e) = &m.ego {
        for l in e.hist.iter().chain(&e.env) {
            g.extend([
                vec![&l.attn.q],
                vec![&l.attn.kv],
                vec![&l.attn.proj],
                vec![&l.mlp.fc],
                vec![&l.mlp.proj],
            ]);
        }
        g.push(vec![&e.head]);
    }
    for l in m.tar.iter().flat_map(|(t, s)| [t, s]).chain(&m.oar) {
        g.extend([
            vec![&l.attn.q, &l.attn.kv],
            vec![&l.attn.proj],
            vec![&l.mlp.fc],
            vec![&l.mlp.proj],
        ]);
    }
    if let Some((i, o)) = &m.track {
        g.extend([vec![i], vec![o]]);
    }
    g.extend(m.tar_heads.iter().chain(&m.oar_heads).map(|h| vec![h]));
    g
}

/// Uploads `parts` stacked (see [`host_linear`]).
fn stacked<X: Exec>(x: &mut X, p: &mut Prepared, parts: &[&PlainLinear]) -> Result<LinearW> {
    let h = p.take(parts)?;
    Ok(LinearW {
        w: upload(x, Elem::W, &h.w)?,
        b: match &h.b {
            Some(b) => Some(upload(x, Elem::F32, b)?),
            None => None,
        },
        n: h.n,
        k: h.k,
    })
}

fn linear<X: Exec>(x: &mut X, p: &mut Prepared, l: &PlainLinear) -> Result<LinearW> {
    stacked(x, p, &[l])
}

fn norm<X: Exec>(x: &mut X, n: &PlainNorm) -> Result<NormW> {
    Ok(NormW {
        g: upload(x, Elem::F32, &n.g)?,
        b: upload(x, Elem::F32, &n.b)?,
    })
}

fn self_layer<X: Exec>(x: &mut X, p: &mut Prepared, l: &PlainSelf) -> Result<SelfW> {
    Ok(SelfW {
        ln1: norm(x, &l.ln1)?,
        qkv: stacked(x, p, &[&l.attn.q, &l.attn.kv])?,
        proj: linear(x, p, &l.attn.proj)?,
        ln2: norm(x, &l.ln2)?,
        fc: linear(x, p, &l.mlp.fc)?,
        fc2: linear(x, p, &l.mlp.proj)?,
    })
}

fn cross_layer<X: Exec>(x: &mut X, p: &mut Prepared, l: &PlainCross) -> Result<CrossW> {
    Ok(CrossW {
        ln_q: norm(x, &l.ln_q)?,
        ln_ctx: norm(x, &l.ln_ctx)?,
        q: linear(x, p, &l.attn.q)?,
        kv: linear(x, p, &l.attn.kv)?,
        proj: linear(x, p, &l.attn.proj)?,
        ln2: norm(x, &l.ln2)?,
        fc: linear(x, p, &l.mlp.fc)?,
        fc2: linear(x, p, &l.mlp.proj)?,
    })
}

/// `rows` `[r][dim]` through `proj` (`y = x·W + b`), in f32.
fn project(rows: &[f32], dim: usize, proj: &PlainLinear) -> Vec<f32> {
    let e = proj.d_out;
    let mut out = Vec::with_capacity(rows.len() / dim.max(1) * e);
    for row in rows.chunks(dim.max(1)) {
        for j in 0..e {
            let mut acc = 0.0f32;
            for (i, v) in row.iter().enumerate() {
                acc += v * proj.w[i * e + j];
            }
            out.push(acc + proj.b.as_ref().map_or(0.0, |b| b[j]));
        }
    }
    out
}

impl Weights {
    /// Uploads `m`'s weights.
    pub(super) fn upload<X: Exec>(x: &mut X, m: &PlainBackbone) -> Result<Self> {
        let spec = &m.spec;
        let e = m.embed.e;
        let mut p = Prepared::of(&groups(m));
        let p = &mut p;
        let (mut table, mut row_base) = (Vec::new(), Vec::new());
        for t in &m.embed.tables {
            row_base.push(i32::try_from(table.len() / e.max(1)).map_err(|_| too_big("embedding table"))?);
            match &t.proj {
                Some(proj) => table.extend(project(&t.rows, t.dim, proj)),
                None => table.extend_from_slice(&t.rows),
            }
        }
        let mut seg_of = vec![0i32; spec.n];
        for (s, seg) in spec.segments.iter().enumerate() {
            seg_of[seg.block_start..seg.block_start + seg.block_len].fill(s as i32);
        }
        let ego = match &m.ego {
            Some(g) => Some(EgoW {
                queries: upload(x, Elem::F32, &g.queries)?,
                q: g.q,
                hist: g
                    .hist
                    .iter()
                    .map(|l| cross_layer(x, p, l))
                    .collect::<Result<_>>()?,
                env: g
                    .env
                    .iter()
                    .map(|l| cross_layer(x, p, l))
                    .collect::<Result<_>>()?,
                ln: norm(x, &g.ln)?,
                head: linear(x, p, &g.head)?,
                block: g.block,
                last: g.last,
            }),
            None => None,
        };
        let w = Self {
            table: upload(x, Elem::F32, &table)?,
            row_base: upload_i32(x, &row_base)?,
            seg_of: upload_i32(x, &seg_of)?,
            pos_emb: upload(x, Elem::F32, &m.embed.pos)?,
            fc1: linear(x, p, &m.embed.fc1)?,
            fc2: linear(x, p, &m.embed.fc2)?,
            time: upload(x, Elem::F32, &m.time)?,
            ego,
            tar: m
                .tar
                .iter()
                .map(|(t, s)| Ok((self_layer(x, p, t)?, self_layer(x, p, s)?)))
                .collect::<Result<_>>()?,
            ln_tar: norm(x, &m.ln_tar)?,
            bos: upload(x, Elem::F32, &m.bos)?,
            oar: m.oar.iter().map(|l| self_layer(x, p, l)).collect::<Result<_>>()?,
            ln_oar: norm(x, &m.ln_oar)?,
            track: match &m.track {
                Some((i, o)) => Some((linear(x, p, i)?, linear(x, p, o)?)),
                None => None,
            },
            tar_heads: m
                .tar_heads
                .iter()
                .map(|h| linear(x, p, h))
                .collect::<Result<_>>()?,
            oar_heads: m
                .oar_heads
                .iter()
                .map(|h| linear(x, p, h))
                .collect::<Result<_>>()?,
        };
        if p.1 > 0 {
            tracing::warn!(
                "{} linear layers were laid out after the others (not in `groups`)",
                p.1
            );
        }
        Ok(w)
    }
}

fn too_big(what: &str) -> GenerateError {
    GenerateError::Settings(format!("{what}: more rows than the kernels' 32-bit indices take"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiled_transpose_equals_the_definition() {
        let (rows, cols) = (70, 131);
        let a: Vec<f32> = (0..rows * cols).map(|i| i as f32).collect();
        let t = transpose(&a, rows, cols);
        for r in 0..rows {
            for c in 0..cols {
                assert_eq!(t[c * rows + r], a[r * cols + c]);
            }
        }
    }
}
