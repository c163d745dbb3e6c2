//! The embedding table's gradient for `Cuda` (burn-fusion over the cubecl backend): one custom operation in
//! the fusion stream that launches `lookup.cu`'s six kernels on cubecl's stream with their buffers bound (as
//! the bias + GELU's are), so the training thread queues it without waiting. Other id types than i32, empty
//! or oversized inputs, or a failure to compile or launch (the first launch of each kernel is checked) run
//! the scatter instead, counted by [`super::fallbacks`].
#![allow(unsafe_code)]

use super::scatter::{FALLBACKS, scatter_grad};
use crate::format::float;
use crate::side::{self, Handles, Inner, Primitive, empty_f32, empty_packed};
use burn::backend::Cuda;
use burn::tensor::{DType, Int, Tensor};
use burn_cubecl::kernel::into_contiguous;
use burn_ir::CustomOpIr;
use cudarc::driver::DeviceRepr;

/// Rows a chunk of the counting sort (`CHUNK` of `lookup.cu`).
const CHUNK: usize = 1024;
/// Sorted rows a tile of the sums (`TILE` of `lookup.cu`).
const TILE: usize = 64;
/// Threads a block of the counting sort's kernels (the kernels' `__launch_bounds__(256)`).
const THREADS: u32 = 256;
/// Threads a block of the two kernels that walk a table row's columns (`d` = 384 or 768: whole passes).
const COLUMN_THREADS: u32 = 128;

/// `LookupSizes` of `lookup.cu`, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct Sizes {
    rows: i64,
    vocab: i32,
    d: i32,
    chunks: i32,
}

// SAFETY: plain old data, laid out as the C struct the kernels take by value.
unsafe impl DeviceRepr for Sizes {}

impl Sizes {
    /// The sizes of a `[rows, d]` gradient into a `vocab`-row table, if the kernels' 32-bit positions and
    /// ids hold them.
    fn new(rows: usize, vocab: usize, d: usize) -> Result<Self, String> {
        let too_big = || format!("{rows} rows into a [{vocab}, {d}] table (over 32-bit sizes)");
        if rows == 0 || vocab == 0 || d == 0 {
            return Err(format!("{rows} rows into a [{vocab}, {d}] table"));
        }
        let int = |x: usize| i32::try_from(x).map_err(|_| too_big());
        // Bucket `vocab` takes the ids outside the table.
        int(vocab + 1)?;
        Ok(Self {
            rows: i64::try_from(rows).map_err(|_| too_big())?,
            vocab: int(vocab)?,
            d: int(d)?,
            chunks: int(rows.div_ceil(CHUNK))?,
        })
    }
}

/// The table's gradient `[vocab, d]` from the output's gradient `g` `[rows, d]` and the ids `[rows]`.
pub(super) fn table_grad(g: Tensor<Cuda, 2>, ids: Tensor<Cuda, 1, Int>, vocab: usize) -> Tensor<Cuda, 2> {
    let [rows, d] = g.dims();
    if let Err(why) = Sizes::new(rows, vocab, d) {
        FALLBACKS.fell_back(&why);
        return scatter_grad(g, ids, vocab);
    }
    let inputs = [side::fused(g), ids.into_primitive()];
    let [grad] = side::register("umgen_lookup_grad", inputs, [vec![vocab, d]], Pass { vocab });
    float(grad)
}

/// The gradient's pass over a `vocab`-row table: g and ids in, the table's gradient out.
#[derive(Debug, Clone, Copy)]
struct Pass {
    vocab: usize,
}

impl side::SidePass for Pass {
    fn outputs(&self, handles: &mut Handles, desc: &CustomOpIr) -> Vec<Primitive> {
        let (inputs, _) = desc.as_fixed::<2, 1>();
        let g = into_contiguous(handles.get_float_tensor::<Inner>(&inputs[0]));
        let ids = into_contiguous(handles.get_int_tensor::<Inner>(&inputs[1]));
        launch(&g, &ids, self.vocab).unwrap_or_else(|why| {
            FALLBACKS.fell_back(&why);
            let ids = Tensor::<Inner, 1, Int>::from_primitive(ids);
            vec![side::inner(scatter_grad(float::<Inner, 2>(g), ids, self.vocab))]
        })
    }
}

/// The kernels' source as NVRTC compiles it.
fn source() -> Result<String, String> {
    Ok(side::kernel_source(umgen_cuda::source::train::LOOKUP))
}

/// Launches the six kernels over contiguous `g` `[rows, d]` (f32) and `ids` `[rows]` (i32), returning the
/// table's gradient; an error says why it could not (nothing the caller keeps was written, so it may run
/// the scatter instead).
fn launch(g: &Primitive, ids: &Primitive, vocab: usize) -> Result<Vec<Primitive>, String> {
    if g.dtype != DType::F32 || ids.dtype != DType::I32 {
        return Err(format!(
            "{:?} gradient and {:?} ids (the kernels take f32 and i32)",
            g.dtype, ids.dtype
        ));
    }
    let shape = g.meta.shape();
    let (rows, d) = (shape[0], shape[1]);
    let sizes = Sizes::new(rows, vocab, d)?;
    let buckets = vocab + 1;
    let chunks = rows.div_ceil(CHUNK);
    let tiles = rows.div_ceil(TILE);
    let int = |shape: Vec<usize>| empty_packed(g, shape, DType::I32);
    let hist = int(vec![chunks, buckets]);
    let start = int(vec![buckets]);
    let order = int(vec![rows]);
    let sorted = int(vec![rows]);
    let partial = empty_f32(g, vec![2 * tiles, d]);
    let grad = empty_f32(g, vec![vocab, d]);
    let bind = |ts: &[&Primitive]| ts.iter().map(|t| t.handle.clone().binding()).collect();
    let blocks = |n: usize| u32::try_from(n).map_err(|_| format!("{n} blocks"));
    let steps = [
        ("count", blocks(chunks)?, THREADS, bind(&[ids, &hist])),
        (
            "prefix",
            blocks(buckets.div_ceil(THREADS as usize))?,
            THREADS,
            bind(&[&hist, &start]),
        ),
        ("scan", 1, THREADS, bind(&[&start])),
        (
            "place",
            blocks(chunks)?,
            THREADS,
            bind(&[ids, &hist, &start, &order, &sorted]),
        ),
        (
            "sum",
            blocks(tiles)?,
            COLUMN_THREADS,
            bind(&[g, &order, &sorted, &grad, &partial]),
        ),
        (
            "finish",
            blocks(vocab)?,
            COLUMN_THREADS,
            bind(&[&start, &partial, &grad]),
        ),
    ];
    for (entry, grid, threads, buffers) in steps {
        // SAFETY: every buffer is bound (cubecl keeps it alive for the launch) and packed, of the extent
        // the kernel indexes: `ids`, `order` and `sorted` `rows`, `g` `rows × d`, `hist` `chunks ×
        // (vocab + 1)`, `start` `vocab + 1`, `partial` `2 · tiles × d`, `grad` `vocab × d`; `sizes` holds
        // the same numbers.
        unsafe {
            side::launch_bound_on_cubecl(
                g,
                &format!("umgen_lookup_{entry}"),
                ("", &source),
                ((grid, 1, 1), threads),
                buffers,
                &sizes,
            )
        }?;
    }
    Ok(vec![grad])
}
