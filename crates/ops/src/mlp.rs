//! The MLP `out(gelu(fc(x)))` ([`gelu_mlp`]) on [`crate::gelu`]'s bias + GELU and the named products.
//!
//! With `train.kernels.recompute_gelu`, its second product does not keep its input: the backward pass
//! recomputes the activation `gelu(y + b)` from the first product `y`, which the bias + GELU operation
//! keeps for its own backward pass anyway, so the step keeps one `[rows, 4d]` tensor less per MLP.

use crate::dispatch::same;
use crate::format::{Precision, float, float_format, operand};
use crate::gelu::{FusedGelu, GeluKernel, linear_gelu, tracked};
use crate::kernels::Kernels;
use crate::linear::linear_with;
use crate::matmul::{NamedMatmul, Weight, Written, backward_biased, finish_op, product_epilogue};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::nn::Linear;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{FloatDType, Tensor};
use std::cell::Cell;

std::thread_local! {
    /// Activations the operation's backward pass recomputed on this thread so far.
    static RECOMPUTED: Cell<u64> = const { Cell::new(0) };
}

/// How many MLP activations the second product's backward pass has recomputed on the calling thread (the
/// thread that runs the backward pass).
pub fn recomputed() -> u64 {
    RECOMPUTED.with(Cell::get)
}

/// An MLP, `out(gelu(fc(x)))`, with [`linear_gelu`]'s hidden activation: where that is bf16, the second
/// product writes the activation's gradient in bf16 too, the format the bias + GELU kernel's backward
/// pass reads (as PyTorch's autocast does).
///
/// With `k.recompute_gelu`, where the bias + GELU runs as one operation, the second product keeps the
/// first product's output (which the GELU keeps anyway) instead of the activation, and its backward pass
/// recomputes the activation ([`GeluProductFn`]).
pub fn gelu_mlp<B: Backend, const D: usize>(
    fc: &Linear<B>,
    out: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    k: &Kernels,
) -> Tensor<B, D> {
    gelu_mlp_onto(None, fc, out, x, p, k)
}

/// [`gelu_mlp`] added to `residual` (f32, the output's shape) where given: with the fused bias + GELU the
/// second product's epilogue adds its bias and the residual stream.
pub fn gelu_mlp_onto<B: Backend, const D: usize>(
    residual: Option<Tensor<B, D>>,
    fc: &Linear<B>,
    out: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    k: &Kernels,
) -> Tensor<B, D> {
    if let (Some(first), Some(op), Some(second), Some(bias), Some(out_b)) = (
        crate::matmul::named_for::<B>(k),
        tracked::<B>(k),
        gelu_product_for::<B>(k),
        &fc.bias,
        &out.bias,
    ) {
        let format = p.operand_dtype();
        let written = Written {
            out: format,
            dx: FloatDType::F32,
        };
        let (y, dims) = crate::linear::product_rows(first, x, fc.weight.val(), p, written, k);
        let h = op(y.clone(), bias.val());
        let written = Written {
            out: FloatDType::F32,
            dx: format,
        };
        let mut dims_out = dims;
        dims_out[D - 1] = out.weight.dims()[1];
        let n = dims_out[D - 1] as i32;
        let residual = residual.map(|r| r.cast(FloatDType::F32).reshape([-1, n]));
        let z = second(
            (h, y, bias.val()),
            (out.weight.val(), out_b.val()),
            residual,
            p,
            written,
            k,
        );
        return z.reshape(dims_out);
    }
    let h = linear_gelu(fc, x, p, k);
    let dx = float_format(h.dtype());
    match residual {
        Some(r) => crate::linear::linear_residual(out, h, r, p, dx, k),
        None => linear_with(out, h, p, dx, k),
    }
}

/// What both passes need: the named products and the bias + GELU passes.
pub trait GeluProductBackend: NamedMatmul + FusedGelu {}
impl<B: NamedMatmul + FusedGelu> GeluProductBackend for B {}

/// `h · w + c (+ add)` (`h = gelu(y + b)` `[rows, n]`, as the bias + GELU operation wrote it from `y` and
/// `b`; `c` the second layer's bias; `add` f32 rows of the result's shape, the residual stream) on the
/// named kernel, the bias and the added rows in its epilogue, operands in `p`'s format, the result and
/// `h`'s gradient in the `written` formats; the backward pass recomputes `h` from `y` and `b` instead of
/// keeping it.
pub type GeluProductFn<B> =
    fn(Hidden<B>, Second<B>, Option<Tensor<B, 2>>, Precision, Written, &Kernels) -> Tensor<B, 2>;

/// The hidden activation `h`, the first product `y` and the first bias `b` it was made of.
pub type Hidden<B> = (Tensor<B, 2>, Tensor<B, 2>, Tensor<B, 1>);

/// The second layer's weight and bias.
pub type Second<B> = (Tensor<B, 2>, Tensor<B, 1>);

/// The operation on `B` when `B` is a training backend and `k` asks for it (with the named products and
/// the fused bias + GELU, whose passes it reuses); `None` otherwise.
pub fn gelu_product_for<B: Backend>(k: &Kernels) -> Option<GeluProductFn<B>> {
    if !k.recompute_gelu || k.gelu == GeluKernel::Burn || k.matmul == crate::kernels::MatmulKernel::Burn {
        return None;
    }
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// [`apply`] on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: GeluProductBackend>() -> Option<GeluProductFn<B>> {
    let plain: GeluProductFn<Autodiff<I, NoCheckpointing>> = apply::<I, NoCheckpointing>;
    let balanced: GeluProductFn<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass: `N` = 3 parents (h, w, c), or 4 with the added rows.
#[derive(Debug)]
struct GeluProduct<const N: usize>;

/// The first product and the bias (`h`'s recipe), and the second product's [`Weight`].
type Kept<I> = (FloatTensor<I>, FloatTensor<I>, Weight<I>);

impl<I: GeluProductBackend, const N: usize> Backward<I, N> for GeluProduct<N> {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, N>, grads: &mut Gradients, _: &mut Checkpointer) {
        let ids = ops.parents.map(|p| p.map(|node| node.id));
        let (y, b, weight) = ops.state;
        let p = weight.1;
        // The weight's gradient reads `h`, recomputed here instead of kept.
        let recompute = || {
            RECOMPUTED.with(|n| n.set(n.get() + 1));
            operand(I::bias_gelu_forward(float(y), float(b)), p)
        };
        backward_biased::<I>(&ids, grads.consume::<I>(&ops.node), weight, recompute, grads);
    }
}

/// [`GeluProductFn`] on `Autodiff<I, C>`: the nodes of `h`, `w`, `c` (and the added rows) are the parents;
/// `y` and `b` are only read.
fn apply<I: GeluProductBackend, C: CheckpointStrategy>(
    (h, y, b): Hidden<Autodiff<I, C>>,
    (w, c): Second<Autodiff<I, C>>,
    add: Option<Tensor<Autodiff<I, C>, 2>>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 2> {
    let (h, w, c) = (
        h.into_primitive().tensor(),
        w.into_primitive().tensor(),
        c.into_primitive().tensor(),
    );
    let add = add.map(|a| a.into_primitive().tensor());
    let wi = operand(float::<I, 2>(w.primitive), p);
    let z = product_epilogue(
        operand(float::<I, 2>(h.primitive), p),
        wi.clone(),
        (
            Some(float(c.primitive)),
            add.as_ref().map(|a| float(a.primitive.clone())),
        ),
        written.out,
        k,
    )
    .into_primitive()
    .tensor();
    let state = || {
        let y = y.into_primitive().tensor().primitive;
        let b = b.into_primitive().tensor().primitive;
        (y, b, (wi.into_primitive().tensor(), p, written.dx, *k))
    };
    let z = match add {
        Some(a) => finish_op!(C, GeluProduct::<4>, [h.node, w.node, c.node, a.node], state(), z),
        None => finish_op!(C, GeluProduct::<3>, [h.node, w.node, c.node], state(), z),
    };
    float(z)
}
