//! Embedding lookups whose table gradient is summed by many units at once.
//!
//! burn's embedding gradient is `select_assign` into a zero table, and cubecl's `select_assign` kernel
//! gives each of the table's `d` columns one unit that walks every looked-up row in turn: 36,864 map
//! tokens of a `small` step walked by 32 … 384 units took 6–13 ms per table (profile, docs/decisions/007-memory-bound-training-kernels.md).
//! [`embed`] is a custom autodiff operation on the training backends whose forward pass is burn's lookup.
//! On CUDA its backward pass is a counting sort of the ids and a walk over the sorted rows (`lookup/cuda.rs`,
//! umgen-cuda's `kernels/train/lookup.cu`: a unit per row or per column of a tile at each step, the rows of each id summed in
//! their order). On the other training backends it splits the rows into `k` chunks, scatters each chunk
//! into its own copy of the table (`scatter` along the vocabulary axis of a `[k, vocab, d]` zero tensor, `k ·
//! d` units of `rows / k` rows each) and sums the copies. Elsewhere it is burn's lookup.

#[cfg(feature = "cuda")]
mod cuda;
mod scatter;

use crate::dispatch::same;
use crate::format::float;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::nn::Embedding;
use burn::tensor::backend::Backend;
use burn::tensor::module::embedding;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Int, Tensor, TensorMetadata};
use scatter::{FALLBACKS, scatter_grad};

/// How many table gradients the CUDA kernels refused or failed to launch in this process (the scatter
/// summed them instead).
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}

/// Rows `[m, l, d]` of `table` for ids `[m, l]`.
pub fn embed<B: Backend>(table: &Embedding<B>, ids: Tensor<B, 2, Int>) -> Tensor<B, 3> {
    rows(table.weight.val(), ids)
}

/// Rows `[m, l, d]` of the matrix `table` `[vocab, d]` for ids `[m, l]` (in `0..vocab`), with [`embed`]'s
/// backward pass on the training backends.
pub fn rows<B: Backend>(table: Tensor<B, 2>, ids: Tensor<B, 2, Int>) -> Tensor<B, 3> {
    match tracked::<B>() {
        Some(op) => op(table, ids),
        None => embedding(table, ids),
    }
}

/// Whether `B` is a training backend on which [`rows`] is the custom operation.
pub fn has_tracked<B: Backend>() -> bool {
    tracked::<B>().is_some()
}

/// The custom operation, when `B` is a training backend.
fn tracked<B: Backend>() -> Option<LookupFn<B>> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// A lookup on `B`.
type LookupFn<B> = fn(Tensor<B, 2>, Tensor<B, 2, Int>) -> Tensor<B, 3>;

/// [`apply`] on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: Backend>() -> Option<LookupFn<B>> {
    let plain: LookupFn<Autodiff<I>> = apply::<I, NoCheckpointing>;
    let balanced: LookupFn<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// A table's gradient on `B`.
#[cfg(feature = "cuda")]
type GradFn<B> = fn(Tensor<B, 2>, Tensor<B, 1, Int>, usize) -> Tensor<B, 2>;

/// The table's gradient `[vocab, d]` from the output's gradient `g` `[rows, d]` and the ids `[rows]`: the
/// CUDA kernels where `I` is `Cuda`, else [`scatter_grad`].
fn table_grad<I: Backend>(g: Tensor<I, 2>, ids: Tensor<I, 1, Int>, vocab: usize) -> Tensor<I, 2> {
    #[cfg(feature = "cuda")]
    if let Some(f) = same::<GradFn<burn::backend::Cuda>, GradFn<I>>(cuda::table_grad) {
        return f(g, ids, vocab);
    }
    scatter_grad(g, ids, vocab)
}

#[derive(Debug)]
struct Lookup;

impl<I: Backend> Backward<I, 1> for Lookup {
    /// The ids and the table's row count.
    type State = (Tensor<I, 1, Int>, usize);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let g = grads.consume::<I>(&ops.node);
        let [node] = ops.parents;
        let Some(node) = node else { return };
        let (ids, vocab) = ops.state;
        let shape = g.shape();
        let d = shape[shape.num_dims() - 1];
        let g = float::<I, 3>(g).reshape([-1, d as i32]);
        grads.register::<I>(node.id, table_grad(g, ids, vocab).into_primitive().tensor());
    }
}

/// The lookup as one operation on `Autodiff<I, C>`.
fn apply<I: Backend, C: CheckpointStrategy>(
    weight: Tensor<Autodiff<I, C>, 2>,
    ids: Tensor<Autodiff<I, C>, 2, Int>,
) -> Tensor<Autodiff<I, C>, 3> {
    let w = weight.into_primitive().tensor();
    let ids = Tensor::<I, 2, Int>::from_primitive(ids.into_primitive());
    let table = float::<I, 2>(w.primitive.clone());
    let vocab = table.dims()[0];
    let y: FloatTensor<I> = embedding(table, ids.clone()).into_primitive().tensor();
    let out = match Lookup.prepare::<C>([w.node.clone()]).compute_bound().stateful() {
        OpsKind::Tracked(prep) => prep.finish((ids.flatten(0, 1), vocab), y),
        OpsKind::UnTracked(prep) => prep.finish(y),
    };
    float(out)
}

#[cfg(test)]
mod tests {
    use super::scatter::chunks;
    use super::*;
    use burn::backend::Flex;
    use burn::nn::EmbeddingConfig;
    use burn::tensor::{Distribution, TensorData};

    type A = Autodiff<Flex>;

    #[test]
    fn chunks_divide_the_rows_and_bound_the_copies() {
        // 36 frames × 704 agent slots, a 1,030-row table of width 384: 84 copies fit 128 MiB,
        // 72 divides the rows.
        assert_eq!(chunks(25_344, 1030, 384), 72);
        assert_eq!(chunks(36 * 1024, 8194, 64), 48);
        assert_eq!(chunks(7, 10, 4), 1);
        assert_eq!(chunks(1031 * 8, 10, 4), 8);
    }

    /// The lookup and the table's gradient equal burn's, with repeated ids (a pad-like id in most rows)
    /// over a row count that takes several chunks.
    #[test]
    fn matches_burns_lookup_and_gradient() {
        let dev = Default::default();
        let table = EmbeddingConfig::new(12, 5).init::<A>(&dev);
        let ids: Vec<i64> = (0..6 * 40)
            .map(|i| if i % 3 == 0 { (i * 7) % 12 } else { 11 })
            .collect();
        let ids = Tensor::<A, 2, Int>::from_data(TensorData::new(ids, [6, 40]), &dev);
        assert!(chunks(240, 12, 5) > 1);
        let w = Tensor::<A, 3>::random([6, 40, 5], Distribution::Normal(0.0, 1.0), &dev);

        let ours = embed(&table, ids.clone());
        let theirs = embedding(table.weight.val(), ids);
        let diff = |a: Tensor<Flex, 2>, b: Tensor<Flex, 2>| (a - b).abs().max().into_scalar();
        assert_eq!(
            diff(
                ours.clone().inner().flatten(0, 1),
                theirs.clone().inner().flatten(0, 1)
            ),
            0.0
        );
        let g_ours = (ours * w.clone()).sum().backward();
        let g_theirs = (theirs * w).sum().backward();
        let weight = table.weight.val();
        let (a, b) = (
            weight.grad(&g_ours).expect("grad"),
            weight.grad(&g_theirs).expect("grad"),
        );
        // Sums of up to 160 terms in two orders: within f32 rounding of the largest sum (an absolute 1e-5
        // failed about once in a few dozen runs, for sums near 20).
        let scale = b.clone().abs().max().into_scalar().max(1.0);
        let d = diff(a, b);
        assert!(d < 1e-6 * scale * 160.0, "{d} at scale {scale}");
    }
}
