//! The forward pass's kernel (the helpers and the layout it shares with the backward pass are in the parent
//! module).

use super::super::{acc_stride, prob_stride, score_stride, tile_stride};
use super::*;

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
