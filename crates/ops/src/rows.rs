//! Per-feature biases added to every row of an activation, with their gradients summed in two stages.
//!
//! burn's autodiff reduces a broadcast operand's gradient one broadcast axis at a time, in axis order. For
//! activations `[32, 2199, 384]` (the `small` preset) the last of those sums runs down 2,199 rows with only
//! 384 outputs, and cubecl's reduction gives each output one unit that walks its column alone: a profiled
//! `small` step spent 41 ms in 37 such sums of 1.1 ms each (docs/decisions/007-memory-bound-training-kernels.md), where the data they read
//! takes 0.04 ms. [`add`] is a custom autodiff operation on the training backends whose forward pass is
//! burn's broadcast (so element-wise fusion around it is unchanged) and whose backward pass sums the rows
//! with `sum`: rows in groups, then the groups (on CUDA one kernel each, umgen-cuda's `kernels/train/rows.cu`, whose blocks
//! read whole row segments; burn's reductions of the groups gave each column one unit, 15–20 µs for a
//! `[256, 384]` matrix). The layer norms' scales and shifts (`norm.rs`) and the layers run as one operation
//! (`layer/math.rs`) use `sum` in their hand-written backward passes. Elsewhere (inference backends,
//! backends this workspace does not train on) [`add`] is burn's broadcast.

#[cfg(feature = "cuda")]
mod cuda;
mod staged;

use crate::dispatch::same;
use crate::format::float;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::backend::Backend;
use burn::tensor::{FloatDType, Shape, Tensor, TensorMetadata};
use staged::{FALLBACKS, staged};

/// How many row sums the CUDA kernel refused or failed to launch in this process (burn's staged reduction
/// summed them instead).
pub fn fallbacks() -> usize {
    FALLBACKS.count()
}

/// Column sums of `[rows, d]` on `B`.
#[cfg(feature = "cuda")]
type SumFn<B> = fn(Tensor<B, 2>) -> Tensor<B, 1>;

/// Sum over every row of `[.., d]` (f32 or bf16): `[d]` in f32. In two stages (rows in groups, then the groups): burn's reduction
/// of a `[70,368, 384]` matrix along its rows in one go gives each column one unit. On CUDA the stages are
/// umgen-cuda's `kernels/train/rows.cu`'s kernel; elsewhere [`staged`].
pub(crate) fn sum<I: Backend, const D: usize>(x: Tensor<I, D>) -> Tensor<I, 1> {
    let d = x.dims()[D - 1];
    let x = x.reshape([-1, d as i32]);
    #[cfg(feature = "cuda")]
    if let Some(f) = same::<SumFn<burn::backend::Cuda>, SumFn<I>>(cuda::sum) {
        return f(x);
    }
    staged(x)
}

/// `x` `[rows, d]` in `format`, and its column sums `[d]` in f32 (of `x` as given): on CUDA one pass for
/// f32 rows going to bf16 (`rows.cu` writes the copy as it sums; a cast of its own, then the sum, read the
/// rows twice, and burn's cast here left a layout the sum and the next product each copied).
pub(crate) fn sum_cast<I: Backend>(x: Tensor<I, 2>, format: FloatDType) -> (Tensor<I, 2>, Tensor<I, 1>) {
    #[cfg(feature = "cuda")]
    if x.dtype() == burn::tensor::DType::F32 && format == FloatDType::BF16 {
        type SumCast<B> = fn(Tensor<B, 2>) -> (Tensor<B, 2>, Tensor<B, 1>);
        if let Some(f) = same::<SumCast<burn::backend::Cuda>, SumCast<I>>(cuda::sum_cast) {
            return f(x);
        }
    }
    (x.clone().cast(format), sum(x))
}

/// [`add_for`] on `B`.
type RowOp<B, const D: usize> = fn(Tensor<B, D>, Tensor<B, 1>, Option<FloatDType>) -> Tensor<B, D>;

/// `x + p` over the last axis (a linear layer's bias), in `x`'s format.
pub fn add<B: Backend, const D: usize>(x: Tensor<B, D>, p: Tensor<B, 1>) -> Tensor<B, D> {
    add_for(x, p, None)
}

/// [`add`] whose backward pass passes the incoming gradient on to `x` in `grad` (where given): where `x`
/// is a product whose backward pass reads its gradient in bf16, the bias's gradient (f32) is summed and the
/// bf16 copy written in one pass (`sum_cast`), where the sum and then the product's cast read it twice.
pub fn add_for<B: Backend, const D: usize>(
    x: Tensor<B, D>,
    p: Tensor<B, 1>,
    grad: Option<FloatDType>,
) -> Tensor<B, D> {
    match tracked::<B, D>() {
        Some(op) => op(x, p, grad),
        None => x + p.unsqueeze::<D>(),
    }
}

/// The custom operation when `B` is a training backend.
fn tracked<B: Backend, const D: usize>() -> Option<RowOp<B, D>> {
    let found = on::<B, burn::backend::Flex, D>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(|| on::<B, burn::backend::Cuda, D>());
    found
}

/// The operation on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: Backend, const D: usize>() -> Option<RowOp<B, D>> {
    let plain: RowOp<Autodiff<I>, D> = apply::<I, NoCheckpointing, D>;
    let balanced: RowOp<Autodiff<I, BalancedCheckpointing>, D> = apply::<I, BalancedCheckpointing, D>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass of [`add`].
#[derive(Debug)]
struct Rows;

impl<I: Backend> Backward<I, 2> for Rows {
    /// The format the gradient is cast to first, if any.
    type State = Option<FloatDType>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let g = grads.consume::<I>(&ops.node);
        let shape = g.shape();
        let d = shape[shape.num_dims() - 1];
        let flat = float::<I, 2>(I::float_reshape(g, Shape::new([shape.num_elements() / d, d])));
        let (flat, db) = match ops.state {
            Some(format) => sum_cast(flat, format),
            None => (flat.clone(), sum(flat)),
        };
        let [x_node, p_node] = ops.parents;
        // Each gradient only for a parent that asks for it (a frozen parameter, an untracked input).
        if let Some(node) = p_node {
            grads.register::<I>(node.id, db.into_primitive().tensor());
        }
        if let Some(node) = x_node {
            let flat = flat.into_primitive().tensor();
            grads.register::<I>(node.id, I::float_reshape(flat, shape));
        }
    }
}

/// [`add_for`] as one operation on `Autodiff<I, C>`.
fn apply<I: Backend, C: CheckpointStrategy, const D: usize>(
    x: Tensor<Autodiff<I, C>, D>,
    p: Tensor<Autodiff<I, C>, 1>,
    grad: Option<FloatDType>,
) -> Tensor<Autodiff<I, C>, D> {
    let (x, p) = (x.into_primitive().tensor(), p.into_primitive().tensor());
    // A bf16 `x` (a product written for a bf16 consumer) gets the bias rounded to bf16, added in its format.
    let format = crate::format::float_format(x.primitive.dtype());
    let bias = float::<I, 1>(p.primitive.clone()).cast(format);
    let y = float::<I, D>(x.primitive.clone()) + bias.unsqueeze::<D>();
    let y = y.into_primitive().tensor();
    let out = match Rows
        .prepare::<C>([x.node.clone(), p.node.clone()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(grad, y),
        OpsKind::UnTracked(prep) => prep.finish(y),
    };
    float(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::tensor::{DType, Distribution};

    type A = Autodiff<Flex>;

    #[test]
    fn training_backends_take_the_operation() {
        assert!(tracked::<A, 3>().is_some());
        assert!(tracked::<Autodiff<Flex, BalancedCheckpointing>, 4>().is_some());
        assert!(tracked::<Flex, 3>().is_none());
    }

    /// Two stages with a remainder (1,000 rows: 256 groups of 3, 232 left) against one.
    #[test]
    fn sum_in_stages_is_the_plain_sum() {
        let x = Tensor::<Flex, 3>::random([4, 250, 6], Distribution::Normal(0.0, 1.0), &Default::default());
        close(sum(x.clone()), x.reshape([1000, 6]).sum_dim(0).reshape([6]), 1e-5);
    }

    /// The value and both gradients equal plain broadcasting's, on 4 × 1026 = 4104 rows (256 groups of 16,
    /// 8 left).
    #[test]
    fn bias_add_matches_broadcasting() {
        let dev = Default::default();
        let bias = Tensor::<A, 1>::random([24], Distribution::Normal(0.0, 1.0), &dev).require_grad();
        let x = Tensor::<A, 3>::random([4, 1026, 24], Distribution::Normal(0.5, 2.0), &dev).require_grad();
        let w = Tensor::<A, 3>::random([4, 1026, 24], Distribution::Normal(0.0, 1.0), &dev);
        let ours = add(x.clone(), bias.clone());
        let theirs = x.clone() + bias.clone().unsqueeze::<3>();
        let flat = |t: Tensor<A, 3>| t.inner().flatten::<1>(0, 2);
        close(flat(ours.clone()), flat(theirs.clone()), 1e-6);
        let g_ours = (ours * w.clone()).sum().backward();
        let g_theirs = (theirs * w).sum().backward();
        close(
            x.grad(&g_ours).expect("x").flatten::<1>(0, 2),
            x.grad(&g_theirs).expect("x").flatten::<1>(0, 2),
            1e-6,
        );
        close(
            bias.grad(&g_ours).expect("bias"),
            bias.grad(&g_theirs).expect("bias"),
            1e-4,
        );
    }

    /// With a gradient format, `x`'s gradient is the incoming one rounded to it, and the bias's (f32) is the
    /// sum of the incoming values as they came.
    #[test]
    fn bias_add_passes_the_gradient_on_in_its_format() {
        let dev = Default::default();
        let bias = Tensor::<A, 1>::random([16], Distribution::Normal(0.0, 1.0), &dev).require_grad();
        let x = Tensor::<A, 2>::random([300, 16], Distribution::Normal(0.0, 1.0), &dev).require_grad();
        let w = Tensor::<Flex, 2>::random([300, 16], Distribution::Normal(0.0, 1.0), &dev);
        let y = add_for(x.clone(), bias.clone(), Some(FloatDType::BF16));
        let g = (y * Tensor::from_inner(w.clone())).sum().backward();
        let dx = x.grad(&g).expect("x");
        assert_eq!(dx.dtype(), DType::BF16);
        let rounded = w.clone().cast(FloatDType::BF16).cast(FloatDType::F32);
        let values = |t: Tensor<Flex, 2>| t.cast(FloatDType::F32).into_data().to_vec::<f32>().expect("f32");
        assert_eq!(values(dx), values(rounded));
        let db = bias.grad(&g).expect("bias");
        assert_eq!(db.dtype(), DType::F32);
        close(db, w.sum_dim(0).reshape([16]), 1e-6);
    }

    fn close(a: Tensor<Flex, 1>, b: Tensor<Flex, 1>, tol: f32) {
        let scale = b.clone().abs().max().into_scalar().max(1e-6);
        let err = (a - b).abs().max().into_scalar() / scale;
        assert!(err < tol, "relative error {err}");
    }
}
