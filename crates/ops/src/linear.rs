//! Linear layers in the products' format ([`crate::format`]): on the training backends the product runs on
//! the named kernel ([`crate::matmul`]) as one `[m, k] × [k, n]` product over all leading dimensions, the
//! bias (and, in [`linear_residual`], the residual stream the layer joins) added by the product's epilogue
//! (`matmul::biased`) in the format the consumer reads; a layer without a bias adds nothing.

use crate::format::{Precision, operand, widen};
use crate::kernels::Kernels;
use crate::matmul::Written;
use burn::nn::Linear;
use burn::tensor::backend::Backend;
use burn::tensor::{FloatDType, Tensor};

/// `x · w` over the last axis of `x` as one `[m, k] × [k, n]` product by `product` (the named kernel, over
/// all leading dimensions at once), written in the `written` formats: the `[m, n]` rows, and the
/// dimensions they take back (`x`'s, the last one `n`).
pub(crate) fn product_rows<B: Backend, const D: usize>(
    product: crate::matmul::ProductFn<B>,
    x: Tensor<B, D>,
    w: Tensor<B, 2>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> (Tensor<B, 2>, [usize; D]) {
    let mut dims = x.dims();
    let inner = dims[D - 1];
    dims[D - 1] = w.dims()[1];
    (product(x.reshape([-1, inner as i32]), w, p, written, k), dims)
}

/// `layer.forward(x)` with the product in `p`'s format, the bias added in f32. Training on CUDA runs the
/// product on the named kernel (`matmul.rs`), as one `[m, k] × [k, n]` product over all leading dimensions.
pub fn linear<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    k: &Kernels,
) -> Tensor<B, D> {
    linear_with(layer, x, p, FloatDType::F32, k)
}

/// `layer.forward(x)` in `format`, the format its consumer reads (bf16 attention operands): on the named
/// kernel the product is written in it and the bias added in it, where [`linear`] writes f32 and the
/// consumer casts (three passes over the result instead of one). The gradient comes back in any format.
pub fn linear_in<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    format: FloatDType,
    k: &Kernels,
) -> Tensor<B, D> {
    let Some(product) = crate::matmul::named_for::<B>(k).filter(|_| format != FloatDType::F32) else {
        return linear(layer, x, p, k).cast(format);
    };
    let written = Written {
        out: format,
        dx: FloatDType::F32,
    };
    // A layer with a bias takes it in the product's epilogue; one without is the product alone.
    if let Some(y) = biased(layer, x.clone(), None, p, written, k) {
        return y;
    }
    let (y, dims) = product_rows(product, x, layer.weight.val(), p, written, k);
    y.reshape(dims)
}

/// [`linear`] whose input's gradient is written in `dx` where the named kernel computes it: the MLP's
/// second layer (its input's gradient only feeds the bias + GELU kernel's backward pass, which reads bf16)
/// and the attention's output projection (flash2's backward pass reads the output's gradient in bf16).
pub fn linear_with<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    dx: FloatDType,
    k: &Kernels,
) -> Tensor<B, D> {
    let written = Written {
        out: FloatDType::F32,
        dx,
    };
    if let Some(y) = biased(layer, x.clone(), None, p, written, k) {
        return y;
    }
    let w = layer.weight.val();
    let y = match (crate::matmul::named_for::<B>(k), p) {
        // No bias (`biased` takes every layer that has one).
        (Some(product), _) => {
            let (y, dims) = product_rows(product, x, w, p, written, k);
            return y.reshape(dims);
        }
        // burn's layer adds the bias inside its product.
        (None, Precision::F32) => return layer.forward(x),
        (None, Precision::Bf16 | Precision::Bf16Linear) => widen(
            burn::tensor::module::linear(operand(x, p), operand(w, p), None),
            p,
        ),
    };
    // Off the training backends `add_for` is burn's broadcast.
    match &layer.bias {
        Some(bias) => crate::rows::add_for(y, bias.val(), Some(p.operand_dtype())),
        None => y,
    }
}

/// `residual + layer.forward(x)` in f32, `x`'s gradient written in `dx` (as [`linear_with`]): on the
/// training backends the bias and the residual stream are summed by the product's epilogue, where they
/// were an element-wise pass of their own.
pub fn linear_residual<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    residual: Tensor<B, D>,
    p: Precision,
    dx: FloatDType,
    k: &Kernels,
) -> Tensor<B, D> {
    let written = Written {
        out: FloatDType::F32,
        dx,
    };
    let residual = residual.cast(FloatDType::F32);
    match biased(layer, x.clone(), Some(residual.clone()), p, written, k) {
        Some(y) => y,
        None => residual + linear_with(layer, x, p, dx, k),
    }
}

/// `x · w + b (+ add)` as [`crate::matmul::biased_autodiff`]'s one operation over all leading dimensions,
/// where the backend trains with the named products and the layer has a bias; `None` otherwise (nothing
/// was computed).
fn biased<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    add: Option<Tensor<B, D>>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> Option<Tensor<B, D>> {
    let op = crate::matmul::biased_for::<B>(k)?;
    let bias = layer.bias.as_ref()?;
    let w = layer.weight.val();
    let mut dims = x.dims();
    let inner = dims[D - 1];
    dims[D - 1] = w.dims()[1];
    let n = dims[D - 1] as i32;
    let add = add.map(|a| a.reshape([-1, n]));
    let y = op((x.reshape([-1, inner as i32]), w, bias.val()), add, p, written, k);
    Some(y.reshape(dims))
}
