//! The backward pass's two kernels: key/value gradients and query gradients (the helpers and the layout
//! they share are in the parent module).

use super::super::{acc_stride, prob_stride, score_stride, tile_stride};
use super::*;

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
