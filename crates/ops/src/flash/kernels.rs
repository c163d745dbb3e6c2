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
//!
//! This module holds what the kernels share (offsets, masks, loads, the tensor-core products); the kernels
//! themselves are in `forward_pass.rs` and `backward_pass.rs`.

// The kernels' language has no `usize::div_ceil`.
#![allow(clippy::manual_div_ceil)]

use super::BLOCK;
use cubecl::cmma;
use cubecl::cmma::{MatrixIdent, MatrixLayout};
use cubecl::prelude::*;

pub(super) mod backward_pass;
pub(super) mod forward_pass;

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
    // an H200 (`umgen-kernel-bench attention`, docs/decisions/005-training-attention-flash2.md).
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
