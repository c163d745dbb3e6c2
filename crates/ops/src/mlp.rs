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
use crate::matmul::{NamedMatmul, Written, product, product_in};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
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
    if let (Some(first), Some(op), Some(second), Some(bias)) = (
        crate::matmul::named_for::<B>(k),
        tracked::<B>(k),
        gelu_product_for::<B>(k),
        &fc.bias,
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
        let z = second(h, y, bias.val(), out.weight.val(), p, written, k);
        let mut dims_out = dims;
        dims_out[D - 1] = out.weight.dims()[1];
        let z = z.reshape(dims_out);
        // As `linear_with` adds it: the bias's sum writes the product's gradient in its operands' format.
        return match &out.bias {
            Some(b) => crate::rows::add_for(z, b.val(), Some(format)),
            None => z,
        };
    }
    let h = linear_gelu(fc, x, p, k);
    let dx = float_format(h.dtype());
    linear_with(out, h, p, dx, k)
}

/// What both passes need: the named products and the bias + GELU passes.
pub trait GeluProductBackend: NamedMatmul + FusedGelu {}
impl<B: NamedMatmul + FusedGelu> GeluProductBackend for B {}

/// `h · w` (`h = gelu(y + b)` `[rows, n]`, as the bias + GELU operation wrote it from `y` and `b`) on the
/// named kernel, operands in `p`'s format, the result and `h`'s gradient in the `written` formats; the
/// backward pass recomputes `h` from `y` and `b` instead of keeping it.
pub type GeluProductFn<B> =
    fn(Tensor<B, 2>, Tensor<B, 2>, Tensor<B, 1>, Tensor<B, 2>, Precision, Written, &Kernels) -> Tensor<B, 2>;

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

#[derive(Debug)]
struct GeluProduct;

/// The first product and the bias (`h`'s recipe), `w` in the products' format, that format, the input
/// gradient's, the kernels.
type Kept<I> = (
    FloatTensor<I>,
    FloatTensor<I>,
    FloatTensor<I>,
    Precision,
    FloatDType,
    Kernels,
);

impl<I: GeluProductBackend> Backward<I, 2> for GeluProduct {
    type State = Kept<I>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [nh, nw] = ops.parents;
        let (y, b, w, p, dx_format, k) = ops.state;
        let dz = operand(float::<I, 2>(grads.consume::<I>(&ops.node)), p);
        if let Some(node) = nh {
            let dh = product_in(dz.clone(), float::<I, 2>(w).transpose(), dx_format, &k);
            grads.register::<I>(node.id, dh.into_primitive().tensor());
        }
        if let Some(node) = nw {
            RECOMPUTED.with(|n| n.set(n.get() + 1));
            let h = operand(I::bias_gelu_forward(float(y), float(b)), p);
            let dw = product(h.transpose(), dz, &k);
            grads.register::<I>(node.id, dw.into_primitive().tensor());
        }
    }
}

/// [`GeluProductFn`] on `Autodiff<I, C>`: `h`'s node and `w`'s are the parents; `y` and `b` are only read.
fn apply<I: GeluProductBackend, C: CheckpointStrategy>(
    h: Tensor<Autodiff<I, C>, 2>,
    y: Tensor<Autodiff<I, C>, 2>,
    b: Tensor<Autodiff<I, C>, 1>,
    w: Tensor<Autodiff<I, C>, 2>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 2> {
    let (h, w) = (h.into_primitive().tensor(), w.into_primitive().tensor());
    let prep = GeluProduct
        .prepare::<C>([h.node.clone(), w.node.clone()])
        .compute_bound()
        .stateful();
    let wi = operand(float::<I, 2>(w.primitive), p);
    let z = product_in(operand(float::<I, 2>(h.primitive), p), wi.clone(), written.out, k)
        .into_primitive()
        .tensor();
    let z = match prep {
        OpsKind::Tracked(prep) => {
            let y = y.into_primitive().tensor().primitive;
            let b = b.into_primitive().tensor().primitive;
            prep.finish((y, b, wi.into_primitive().tensor(), p, written.dx, *k), z)
        }
        OpsKind::UnTracked(prep) => prep.finish(z),
    };
    float(z)
}
