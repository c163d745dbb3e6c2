//! The fused attention's kernels in cubecl: FlashAttention-2's forward pass and its backward pass split in
//! two (one kernel for the key/value gradients, one for the query gradients, so that no gradient needs an
//! atomic sum across cubes).
//!
//! Layout of every kernel: one cube per block of [`BLOCK`] rows (queries, or keys for the key/value
//! gradients) of one (sequence, head), four planes of 32 units, each plane owning 16 of the rows; the cube
//! loops over the other side (keys, or queries) in steps of `step` rows (a launch constant, [`super::step`]):
//! the step's tiles, scores and probabilities are what fills shared memory, so a shorter step lets more
//! cubes share an SM. Products
//! run on tensor cores (`cmma`) from shared memory: TF32 tiles of 16×16×8 for f32 operands, bf16 tiles of
//! 16×16×16 for bf16 operands, all accumulating in f32 (so `32 / kstep` is the operands' size in bytes,
//! which sets the rows' padding). The element-wise work between products (scale,
//! mask, online softmax, the softmax Jacobian) runs on f32 copies of the products in shared memory, two
//! units per row. Nothing of size `lq × lk` reaches global memory: the memory of a pass is its inputs,
//! outputs and one f32 log-sum-exp per query.
//!
//! Rows past a sequence's end are loaded as zeros and masked out; `off = lk − lq` aligns the causal mask
//! bottom-right, as burn's `is_causal` and the tiled path do.

// The kernels' language has no `usize::div_ceil`.
#![allow(clippy::manual_div_ceil)]

use super::{BLOCK, acc_stride, prob_stride, score_stride, tile_stride};
use cubecl::cmma;
use cubecl::cmma::{MatrixIdent, MatrixLayout};
use cubecl::prelude::*;
/// Units per cube: four planes of 32.
const UNITS: usize = 128;
/// Running maximum of a row that has seen no visible score yet (finite, so that differences stay finite).
const NONE_SEEN: f32 = -1.0e30;

/// Offset of one (sequence, head) in a `[b, h, l, dh]` (or `[b, h, l, 1]`) tensor.
#[cube]
fn head_base<T: CubeType>(t: &Tensor<T>, seq: usize, head: usize) -> usize {
    seq * t.stride(0) + head * t.stride(1)
}

/// Whether `key` is visible from `query`.
#[cube]
fn visible(key: usize, query: usize, lk: usize, lq: usize, off: usize, #[comptime] causal: bool) -> bool {
    let mut seen = key < lk && query < lq;
    if causal {
        seen = seen && key <= query + off;
    }
    seen
}

/// Key steps of `step` keys the query block starting at `q0` sees: all of them, or for causal attention
/// those up to its last query's last visible key.
#[cube]
fn key_steps(lk: usize, q0: usize, off: usize, #[comptime] causal: bool, #[comptime] step: usize) -> usize {
    let mut end = lk;
    if causal {
        end = min(lk, q0 + BLOCK + off);
    }
    (end + step - 1) / step
}

/// Copies rows `[row0, row0 + rows)` of one (sequence, head) of `src` (`[b, h, l, dh]`, any strides; rows
/// at or past `valid` as zeros) into `dst` (row stride `stride`), converted to the products' format.
#[cube]
fn load_rows<E: Float, C: Float>(
    src: &Tensor<E>,
    base: usize,
    row0: usize,
    valid: usize,
    dst: &mut SharedMemory<C>,
    #[comptime] rows: usize,
    #[comptime] dh: usize,
    #[comptime] stride: usize,
) {
    let (s2, s3) = (src.stride(2), src.stride(3));
    // A loop, not unrolled: unrolling this and the element-wise loops made the kernels 1.2–1.4× slower on
    // an H200 (`umgen bench attention`, docs/perf-notes.md).
    let mut i = (UNIT_POS_Y * 32 + UNIT_POS_X) as usize;
    while i < comptime!(rows * dh) {
        let r = i / dh;
        let c = i % dh;
        let row = row0 + r;
        let mut x = C::from_int(0);
        if row < valid {
            x = C::cast_from(src[base + row * s2 + c * s3]);
        }
        dst[r * stride + c] = x;
        i += UNITS;
    }
}

/// Sets the first `BLOCK · stride` values of `dst` to zero.
#[cube]
fn zero(dst: &mut SharedMemory<f32>, #[comptime] stride: usize) {
    let mut i = (UNIT_POS_Y * 32 + UNIT_POS_X) as usize;
    while i < comptime!(BLOCK * stride) {
        dst[i] = 0.0;
        i += UNITS;
    }
}

/// The A operand of a 16 × 16 × `kstep` product: 16 rows of `src` from `start`, row stride `stride`.
#[cube]
fn tile_a<C: Float>(
    src: &SharedMemory<C>,
    start: usize,
    #[comptime] stride: usize,
    #[comptime] kstep: usize,
) -> cmma::Matrix<C> {
    let rows = src.slice(start, start + 16 * stride);
    cmma::Matrix::<C>::from_slice(
        MatrixIdent::A,
        16usize,
        16usize,
        kstep,
        MatrixLayout::RowMajor,
        &rows,
        stride as u32,
    )
}

/// The B operand of a 16 × 16 × `kstep` product from `src[start..end]`, row stride `stride`, in
/// `layout`: column-major for rows of keys (`a · bᵀ`), row-major for a block of rows (`a · b`).
#[cube]
fn tile_b<C: Float>(
    src: &SharedMemory<C>,
    start: usize,
    end: usize,
    #[comptime] layout: MatrixLayout,
    #[comptime] stride: usize,
    #[comptime] kstep: usize,
) -> cmma::Matrix<C> {
    let rows = src.slice(start, end);
    cmma::Matrix::<C>::from_slice(
        MatrixIdent::B,
        16usize,
        16usize,
        kstep,
        layout,
        &rows,
        stride as u32,
    )
}

/// One plane's 16 × `step` product `a · bᵀ` into `out` (f32, row stride `so`, from `out_off`): `a` holds
/// the plane's 16 rows of length `dh` from `a_off`, `b` `step` rows of length `dh`; both row stride `sa`.
#[cube]
#[allow(clippy::too_many_arguments)]
fn rows_by_rows<C: Float>(
    a: &SharedMemory<C>,
    a_off: usize,
    b: &SharedMemory<C>,
    out: &mut SharedMemory<f32>,
    out_off: usize,
    #[comptime] dh: usize,
    #[comptime] sa: usize,
    #[comptime] so: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
) {
    #[unroll]
    for nt in 0..step / 16 {
        let acc = cmma::Matrix::<f32>::from_value(
            MatrixIdent::Accumulator,
            16usize,
            16usize,
            kstep,
            MatrixLayout::Undefined,
            0.0,
        );
        #[unroll]
        for kk in 0..dh / kstep {
            let x = tile_a::<C>(a, a_off + kk * kstep, sa, kstep);
            let (b0, b1) = (nt * 16 * sa + kk * kstep, (nt * 16 + 16) * sa);
            let y = tile_b::<C>(b, b0, b1, MatrixLayout::ColMajor, sa, kstep);
            cmma::execute::<C, C, f32, f32>(&x, &y, &acc, &acc);
        }
        cmma::store(
            &mut out.slice_mut(out_off + nt * 16, out_off + nt * 16 + 16 * so),
            &acc,
            so as u32,
            MatrixLayout::RowMajor,
        );
    }
}

/// `sum` plus the plane's product of `a` (16 rows of length `step` from `a_off`, row stride `sa`) and
/// columns `[16 nt, 16 nt + 16)` of `b` (`step` rows, row stride `sb`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn add_product<C: Float>(
    sum: &cmma::Matrix<f32>,
    a: &SharedMemory<C>,
    a_off: usize,
    b: &SharedMemory<C>,
    #[comptime] nt: usize,
    #[comptime] sa: usize,
    #[comptime] sb: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
) {
    #[unroll]
    for kk in 0..step / kstep {
        let x = tile_a::<C>(a, a_off + kk * kstep, sa, kstep);
        let (b0, b1) = (kk * kstep * sb + nt * 16, (kk * kstep + kstep) * sb);
        let y = tile_b::<C>(b, b0, b1, MatrixLayout::RowMajor, sb, kstep);
        cmma::execute::<C, C, f32, f32>(&x, &y, sum, sum);
    }
}

/// One plane's 16 × `dh` accumulator in `acc` (f32, row stride `sacc`, from `acc_off`) plus `a · b`: `a`
/// holds the plane's 16 rows of length `step` from `a_off` (row stride `sa`), `b` `step` rows of length
/// `dh` (row stride `sb`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn accumulate<C: Float>(
    acc: &mut SharedMemory<f32>,
    acc_off: usize,
    a: &SharedMemory<C>,
    a_off: usize,
    b: &SharedMemory<C>,
    #[comptime] dh: usize,
    #[comptime] sa: usize,
    #[comptime] sb: usize,
    #[comptime] sacc: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
) {
    #[unroll]
    for nt in 0..dh / 16 {
        let sum = cmma::Matrix::<f32>::from_value(
            MatrixIdent::Accumulator,
            16usize,
            16usize,
            kstep,
            MatrixLayout::Undefined,
            0.0,
        );
        let start = acc_off + nt * 16;
        cmma::load_with_layout(
            &sum,
            &acc.slice(start, start + 16 * sacc),
            sacc as u32,
            MatrixLayout::RowMajor,
        );
        add_product::<C>(&sum, a, a_off, b, nt, sa, sb, kstep, step);
        cmma::store(
            &mut acc.slice_mut(start, start + 16 * sacc),
            &sum,
            sacc as u32,
            MatrixLayout::RowMajor,
        );
    }
}

/// One plane's 16 × `dh` f32 accumulator held in tensor-core fragments (`dh / 16` tiles of 16 × 16), zero:
/// the backward kernels' sums need no rescaling between steps, so, unlike the forward pass's, they never
/// go through shared memory until the end.
#[cube]
fn zero_tiles(#[comptime] dh: usize, #[comptime] kstep: usize) -> Sequence<cmma::Matrix<f32>> {
    let mut tiles = Sequence::new();
    #[unroll]
    for _ in 0..dh / 16 {
        tiles.push(cmma::Matrix::<f32>::from_value(
            MatrixIdent::Accumulator,
            16usize,
            16usize,
            kstep,
            MatrixLayout::Undefined,
            0.0,
        ));
    }
    tiles
}

/// [`accumulate`] into fragments: `tiles` plus `a · b`, `a` the plane's 16 rows of length `step` from
/// `a_off` (row stride `sa`), `b` `step` rows of length `dh` (row stride `sb`).
#[cube]
#[allow(clippy::too_many_arguments)]
fn accumulate_tiles<C: Float>(
    tiles: &Sequence<cmma::Matrix<f32>>,
    a: &SharedMemory<C>,
    a_off: usize,
    b: &SharedMemory<C>,
    #[comptime] dh: usize,
    #[comptime] sa: usize,
    #[comptime] sb: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
) {
    #[unroll]
    for nt in 0..dh / 16 {
        add_product::<C>(tiles.index(nt), a, a_off, b, nt, sa, sb, kstep, step);
    }
}

/// Stores one plane's fragments into its 16 rows of `acc` (row stride `sacc`, from `acc_off`).
#[cube]
fn store_tiles(
    tiles: &Sequence<cmma::Matrix<f32>>,
    acc: &mut SharedMemory<f32>,
    acc_off: usize,
    #[comptime] dh: usize,
    #[comptime] sacc: usize,
) {
    #[unroll]
    for nt in 0..dh / 16 {
        let start = acc_off + nt * 16;
        cmma::store(
            &mut acc.slice_mut(start, start + 16 * sacc),
            tiles.index(nt),
            sacc as u32,
            MatrixLayout::RowMajor,
        );
    }
}

/// Forward pass: `out = softmax(q kᵀ · scale) v` (f32, `[b, h, lq, dh]`) and each query's log-sum-exp of
/// its scaled scores (f32, `[b, h, lq, 1]`). Cube `(x, y, z)` = (query block, head, sequence).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn forward<E: Float, C: Float>(
    q: &Tensor<E>,
    k: &Tensor<E>,
    v: &Tensor<E>,
    out: &mut Tensor<f32>,
    lse: &mut Tensor<f32>,
    scale: f32,
    off: usize,
    #[comptime] causal: bool,
    #[comptime] dh: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
    #[define(E, C)] _dtypes: [StorageType; 2],
) {
    let sq = comptime!(tile_stride(dh, 32 / kstep));
    let ss = comptime!(score_stride(step));
    let sp = comptime!(prob_stride(step, 32 / kstep));
    let so = comptime!(acc_stride(dh));
    let mut qs = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sq), 128usize);
    let mut ks = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut vs = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut scores = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * ss), 128usize);
    let mut probs = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sp), 128usize);
    let mut acc = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * so), 128usize);

    let (lq, lk) = (q.shape(2), k.shape(2));
    let (seq, head) = (CUBE_POS_Z as usize, CUBE_POS_Y as usize);
    let q0 = CUBE_POS_X as usize * BLOCK;
    let plane = UNIT_POS_Y as usize;
    let half = UNIT_POS_X as usize % 2;
    let r = plane * 16 + UNIT_POS_X as usize / 2;
    let row = q0 + r;

    let kbase = head_base(k, seq, head);
    let vbase = head_base(v, seq, head);
    load_rows::<E, C>(q, head_base(q, seq, head), q0, lq, &mut qs, BLOCK, dh, sq);
    zero(&mut acc, so);

    let mut m = f32::new(NONE_SEEN);
    let mut l = 0.0f32;
    for kb in 0..key_steps(lk, q0, off, causal, step) {
        let k0 = kb * step;
        sync_cube();
        load_rows::<E, C>(k, kbase, k0, lk, &mut ks, step, dh, sq);
        load_rows::<E, C>(v, vbase, k0, lk, &mut vs, step, dh, sq);
        sync_cube();
        rows_by_rows::<C>(
            &qs,
            plane * 16 * sq,
            &ks,
            &mut scores,
            plane * 16 * ss,
            dh,
            sq,
            ss,
            kstep,
            step,
        );
        sync_plane();

        let mut top = f32::new(NONE_SEEN);
        for j in 0..step / 2 {
            let c = half + 2 * j;
            if visible(k0 + c, row, lk, lq, off, causal) {
                top = max(top, scores[r * ss + c] * scale);
            }
        }
        top = max(top, plane_shuffle_xor(top, 1));
        let m_new = max(m, top);
        let mut sum = 0.0f32;
        for j in 0..step / 2 {
            let c = half + 2 * j;
            let s = scores[r * ss + c] * scale;
            let p = select(visible(k0 + c, row, lk, lq, off, causal), (s - m_new).exp(), 0.0);
            probs[r * sp + c] = C::cast_from(p);
            sum += p;
        }
        sum += plane_shuffle_xor(sum, 1);
        let alpha = (m - m_new).exp();
        l = l * alpha + sum;
        m = m_new;
        for j in 0..dh / 2 {
            let c = half + 2 * j;
            acc[r * so + c] = acc[r * so + c] * alpha;
        }
        sync_plane();
        accumulate::<C>(
            &mut acc,
            plane * 16 * so,
            &probs,
            plane * 16 * sp,
            &vs,
            dh,
            sp,
            sq,
            so,
            kstep,
            step,
        );
        sync_plane();
    }

    if row < lq {
        let obase = head_base(out, seq, head) + row * out.stride(2);
        let os3 = out.stride(3);
        for j in 0..dh / 2 {
            let c = half + 2 * j;
            out[obase + c * os3] = acc[r * so + c] / l;
        }
        if half == 0 {
            lse[head_base(lse, seq, head) + row * lse.stride(2)] = m + l.ln();
        }
    }
}

/// Gradients of the keys and values: `dk = scale · dSᵀ q` and `dv = Pᵀ dout` (f32, `[b, h, lk, dh]`), from
/// each query's log-sum-exp and `delta = rowsum(dout ∘ out)` (f32, `[b, h, lq, 1]`). Cube `(x, y, z)` =
/// (key block, head, sequence).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn backward_kv<E: Float, C: Float>(
    q: &Tensor<E>,
    k: &Tensor<E>,
    v: &Tensor<E>,
    dout: &Tensor<E>,
    lse: &Tensor<f32>,
    delta: &Tensor<f32>,
    dk: &mut Tensor<f32>,
    dv: &mut Tensor<f32>,
    scale: f32,
    off: usize,
    #[comptime] causal: bool,
    #[comptime] dh: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
    #[define(E, C)] _dtypes: [StorageType; 2],
) {
    let sq = comptime!(tile_stride(dh, 32 / kstep));
    let ss = comptime!(score_stride(step));
    let sp = comptime!(prob_stride(step, 32 / kstep));
    let so = comptime!(acc_stride(dh));
    let mut ks = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sq), 128usize);
    let mut vs = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sq), 128usize);
    let mut qs = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut dos = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut lses = SharedMemory::<f32>::new_aligned(step, 16usize);
    let mut deltas = SharedMemory::<f32>::new_aligned(step, 16usize);
    let mut st = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * ss), 128usize);
    let mut dpt = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * ss), 128usize);
    let mut pt = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sp), 128usize);
    let mut dst = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sp), 128usize);
    let mut dka = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * so), 128usize);
    let mut dva = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * so), 128usize);

    let (lq, lk) = (q.shape(2), k.shape(2));
    let (seq, head) = (CUBE_POS_Z as usize, CUBE_POS_Y as usize);
    let k0 = CUBE_POS_X as usize * BLOCK;
    let plane = UNIT_POS_Y as usize;
    let half = UNIT_POS_X as usize % 2;
    let r = plane * 16 + UNIT_POS_X as usize / 2;
    let key = k0 + r;
    let tid = (UNIT_POS_Y * 32 + UNIT_POS_X) as usize;

    let qbase = head_base(q, seq, head);
    let dobase = head_base(dout, seq, head);
    let lbase = head_base(lse, seq, head);
    let dbase = head_base(delta, seq, head);
    load_rows::<E, C>(k, head_base(k, seq, head), k0, lk, &mut ks, BLOCK, dh, sq);
    load_rows::<E, C>(v, head_base(v, seq, head), k0, lk, &mut vs, BLOCK, dh, sq);
    let dk_tiles = zero_tiles(dh, kstep);
    let dv_tiles = zero_tiles(dh, kstep);

    // The first query that sees this block's first key.
    let mut first = 0;
    if causal && k0 > off {
        first = (k0 - off) / step;
    }
    let blocks = (lq + step - 1) / step;
    for qb in first..blocks {
        let q0 = qb * step;
        sync_cube();
        load_rows::<E, C>(q, qbase, q0, lq, &mut qs, step, dh, sq);
        load_rows::<E, C>(dout, dobase, q0, lq, &mut dos, step, dh, sq);
        if tid < step {
            let query = q0 + tid;
            let mut x = 0.0f32;
            let mut y = 0.0f32;
            if query < lq {
                x = lse[lbase + query * lse.stride(2)];
                y = delta[dbase + query * delta.stride(2)];
            }
            lses[tid] = x;
            deltas[tid] = y;
        }
        sync_cube();
        rows_by_rows::<C>(
            &ks,
            plane * 16 * sq,
            &qs,
            &mut st,
            plane * 16 * ss,
            dh,
            sq,
            ss,
            kstep,
            step,
        );
        rows_by_rows::<C>(
            &vs,
            plane * 16 * sq,
            &dos,
            &mut dpt,
            plane * 16 * ss,
            dh,
            sq,
            ss,
            kstep,
            step,
        );
        sync_plane();
        for j in 0..step / 2 {
            let c = half + 2 * j;
            let seen = visible(key, q0 + c, lk, lq, off, causal);
            let p = select(seen, (st[r * ss + c] * scale - lses[c]).exp(), 0.0);
            let ds = p * (dpt[r * ss + c] - deltas[c]);
            pt[r * sp + c] = C::cast_from(p);
            dst[r * sp + c] = C::cast_from(ds);
        }
        sync_plane();
        accumulate_tiles::<C>(&dv_tiles, &pt, plane * 16 * sp, &dos, dh, sp, sq, kstep, step);
        accumulate_tiles::<C>(&dk_tiles, &dst, plane * 16 * sp, &qs, dh, sp, sq, kstep, step);
    }
    // Each plane reads back only its own rows; a block with no visible query skips the loop and stores
    // zeros.
    store_tiles(&dk_tiles, &mut dka, plane * 16 * so, dh, so);
    store_tiles(&dv_tiles, &mut dva, plane * 16 * so, dh, so);
    sync_plane();

    if key < lk {
        let kb = head_base(dk, seq, head) + key * dk.stride(2);
        let vb = head_base(dv, seq, head) + key * dv.stride(2);
        let (k3, v3) = (dk.stride(3), dv.stride(3));
        for j in 0..dh / 2 {
            let c = half + 2 * j;
            dk[kb + c * k3] = dka[r * so + c] * scale;
            dv[vb + c * v3] = dva[r * so + c];
        }
    }
}

/// Gradient of the queries: `dq = scale · dS k` (f32, `[b, h, lq, dh]`). Cube `(x, y, z)` = (query block,
/// head, sequence).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn backward_q<E: Float, C: Float>(
    q: &Tensor<E>,
    k: &Tensor<E>,
    v: &Tensor<E>,
    dout: &Tensor<E>,
    lse: &Tensor<f32>,
    delta: &Tensor<f32>,
    dq: &mut Tensor<f32>,
    scale: f32,
    off: usize,
    #[comptime] causal: bool,
    #[comptime] dh: usize,
    #[comptime] kstep: usize,
    #[comptime] step: usize,
    #[define(E, C)] _dtypes: [StorageType; 2],
) {
    let sq = comptime!(tile_stride(dh, 32 / kstep));
    let ss = comptime!(score_stride(step));
    let sp = comptime!(prob_stride(step, 32 / kstep));
    let so = comptime!(acc_stride(dh));
    let mut qs = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sq), 128usize);
    let mut dos = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sq), 128usize);
    let mut ks = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut vs = SharedMemory::<C>::new_aligned(comptime!(step * sq), 128usize);
    let mut s = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * ss), 128usize);
    let mut dp = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * ss), 128usize);
    let mut ds = SharedMemory::<C>::new_aligned(comptime!(BLOCK * sp), 128usize);
    let mut acc = SharedMemory::<f32>::new_aligned(comptime!(BLOCK * so), 128usize);

    let (lq, lk) = (q.shape(2), k.shape(2));
    let (seq, head) = (CUBE_POS_Z as usize, CUBE_POS_Y as usize);
    let q0 = CUBE_POS_X as usize * BLOCK;
    let plane = UNIT_POS_Y as usize;
    let half = UNIT_POS_X as usize % 2;
    let r = plane * 16 + UNIT_POS_X as usize / 2;
    let row = q0 + r;

    let kbase = head_base(k, seq, head);
    let vbase = head_base(v, seq, head);
    load_rows::<E, C>(q, head_base(q, seq, head), q0, lq, &mut qs, BLOCK, dh, sq);
    load_rows::<E, C>(dout, head_base(dout, seq, head), q0, lq, &mut dos, BLOCK, dh, sq);
    let dq_tiles = zero_tiles(dh, kstep);
    let mut my_lse = 0.0f32;
    let mut my_delta = 0.0f32;
    if row < lq {
        my_lse = lse[head_base(lse, seq, head) + row * lse.stride(2)];
        my_delta = delta[head_base(delta, seq, head) + row * delta.stride(2)];
    }

    for kb in 0..key_steps(lk, q0, off, causal, step) {
        let k0 = kb * step;
        sync_cube();
        load_rows::<E, C>(k, kbase, k0, lk, &mut ks, step, dh, sq);
        load_rows::<E, C>(v, vbase, k0, lk, &mut vs, step, dh, sq);
        sync_cube();
        rows_by_rows::<C>(
            &qs,
            plane * 16 * sq,
            &ks,
            &mut s,
            plane * 16 * ss,
            dh,
            sq,
            ss,
            kstep,
            step,
        );
        rows_by_rows::<C>(
            &dos,
            plane * 16 * sq,
            &vs,
            &mut dp,
            plane * 16 * ss,
            dh,
            sq,
            ss,
            kstep,
            step,
        );
        sync_plane();
        for j in 0..step / 2 {
            let c = half + 2 * j;
            let seen = visible(k0 + c, row, lk, lq, off, causal);
            let p = select(seen, (s[r * ss + c] * scale - my_lse).exp(), 0.0);
            ds[r * sp + c] = C::cast_from(p * (dp[r * ss + c] - my_delta));
        }
        sync_plane();
        accumulate_tiles::<C>(&dq_tiles, &ds, plane * 16 * sp, &ks, dh, sp, sq, kstep, step);
    }
    store_tiles(&dq_tiles, &mut acc, plane * 16 * so, dh, so);
    sync_plane();

    if row < lq {
        let base = head_base(dq, seq, head) + row * dq.stride(2);
        let s3 = dq.stride(3);
        for j in 0..dh / 2 {
            let c = half + 2 * j;
            dq[base + c * s3] = acc[r * so + c] * scale;
        }
    }
}
