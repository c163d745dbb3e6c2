//! The pieces both passes of a recomputed layer are built from: layer norms, linear layers and dropout,
//! each with its gradient, on the same kernels and with the same casts as the autodiff path.

use crate::flash::FusedAttention;
use crate::format::Precision;
use crate::format::operand;
use crate::gelu::FusedGelu;
use crate::kernels::{EpilogueKernel, Kernels};
use crate::matmul::{NamedMatmul, product, product_epilogue, product_in};
use crate::norm::FusedNorm;
use crate::temporal::TemporalAttention;
use burn::tensor::{Bool, FloatDType, Tensor};

/// What both passes need from the inner backend: the attention (over positions and over time), matmul,
/// layer-norm and bias + GELU kernels.
pub trait LayerBackend: FusedAttention + TemporalAttention + NamedMatmul + FusedNorm + FusedGelu {}
impl<B: FusedAttention + TemporalAttention + NamedMatmul + FusedNorm + FusedGelu> LayerBackend for B {}

/// A layer norm's scale and shift.
#[derive(Debug, Clone)]
pub struct Norm<I: LayerBackend> {
    pub gamma: Tensor<I, 1>,
    pub beta: Tensor<I, 1>,
}

/// A linear layer's weight `[in, out]` and bias `[out]`.
#[derive(Debug, Clone)]
pub struct Lin<I: LayerBackend> {
    pub w: Tensor<I, 2>,
    pub b: Tensor<I, 1>,
}

/// A dropout keep-mask (true = kept) and the scale of kept values, `1 / (1 − p)`.
pub type Mask<I> = Option<(Tensor<I, 3, Bool>, f64)>;

/// `x` through dropout with `mask`.
pub fn drop<I: LayerBackend>(mask: &Mask<I>, x: Tensor<I, 3>) -> Tensor<I, 3> {
    match mask {
        Some((m, scale)) => x * m.clone().float().mul_scalar(*scale),
        None => x,
    }
}

/// A layer norm's row means and `1/√(var + ε)`, `[rows]`.
pub type Stats<I> = (Tensor<I, 1>, Tensor<I, 1>);

/// `(x − mean) / √(var + ε) · γ + β` over the last axis ([`FusedNorm`]'s kernels) in the products' format
/// under `p` (it feeds products only), with the rows' statistics and, with `keep`, the input in that
/// format (written as the kernel reads it). `x` is f32 or a kept bf16 copy.
pub fn norm<I: LayerBackend>(
    x: Tensor<I, 3>,
    n: &Norm<I>,
    eps: f64,
    p: Precision,
    keep: Option<FloatDType>,
    k: &Kernels,
) -> (Tensor<I, 3>, Stats<I>, Option<Tensor<I, 3>>) {
    let [b, l, d] = x.dims();
    let out = p.operand_dtype();
    let normed = I::norm_forward(
        x.reshape([b * l, d]),
        n.gamma.clone(),
        n.beta.clone(),
        eps,
        (out, keep),
        k,
    );
    let kept = normed.kept.map(|t| t.reshape([b, l, d]));
    (normed.y.reshape([b, l, d]), (normed.mean, normed.rstd), kept)
}

/// Gradients of a layer norm's input, scale and shift from its output's gradient `dy`; the input's
/// gradient with `dres` added where given, the residual stream's gradient of the same input (in the norm's
/// kernel).
pub fn norm_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    (mean, rstd): Stats<I>,
    n: &Norm<I>,
    dy: Tensor<I, 3>,
    dres: Option<Tensor<I, 3>>,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 1>, Tensor<I, 1>) {
    let [b, l, d] = x.dims();
    let flat = |t: Tensor<I, 3>| t.reshape([b * l, d]);
    let (fused, apart) = match k.epilogue {
        EpilogueKernel::Fused => (dres.map(flat), None),
        EpilogueKernel::Apart => (None, dres),
    };
    let (dx, dgamma, dbeta) = I::norm_backward(flat(dy), (flat(x), mean, rstd), n.gamma.clone(), fused, k);
    let dx = dx.reshape([b, l, d]);
    let dx = match apart {
        Some(r) => dx + r,
        None => dx,
    };
    (dx, dgamma, dbeta)
}

/// `x · w` `[b · l, n]` with the product in `p`'s format (as `precision::linear` on the named kernel),
/// written in `out`.
pub fn unbiased<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    p: Precision,
    out: FloatDType,
    k: &Kernels,
) -> Tensor<I, 2> {
    let [b, len, inner] = x.dims();
    product_in(
        operand(x.reshape([b * len, inner]), p),
        operand(l.w.clone(), p),
        out,
        k,
    )
}

/// `x · w + b` with the product in `p`'s format.
pub fn linear<I: LayerBackend>(x: Tensor<I, 3>, l: &Lin<I>, p: Precision, k: &Kernels) -> Tensor<I, 3> {
    linear_in(x, l, p, FloatDType::F32, k)
}

/// [`linear`] written in `format`, the bias added by the product's epilogue.
pub fn linear_in<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    p: Precision,
    format: FloatDType,
    k: &Kernels,
) -> Tensor<I, 3> {
    epilogue(x, l, None, p, format, k)
}

/// `x + drop(input · w + b)` in f32 (a kept bf16 `x` widened first); without dropout the product's
/// epilogue adds the bias and `x`.
pub fn residual<I: LayerBackend>(
    x: Tensor<I, 3>,
    mask: &Mask<I>,
    input: Tensor<I, 3>,
    l: &Lin<I>,
    p: Precision,
    k: &Kernels,
) -> Tensor<I, 3> {
    let x = x.cast(FloatDType::F32);
    match mask {
        None => linear_add(input, l, x, p, k),
        Some(_) => x + drop(mask, linear(input, l, p, k)),
    }
}

/// `x · w + b + add` in f32: a residual stream `add` and the bias summed by the product's epilogue, where
/// each was an element-wise pass over the result.
pub fn linear_add<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    add: Tensor<I, 3>,
    p: Precision,
    k: &Kernels,
) -> Tensor<I, 3> {
    epilogue(x, l, Some(add), p, FloatDType::F32, k)
}

/// `x · w + b (+ add)` in `format` (`product_epilogue`).
fn epilogue<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    add: Option<Tensor<I, 3>>,
    p: Precision,
    format: FloatDType,
    k: &Kernels,
) -> Tensor<I, 3> {
    let [b, len, inner] = x.dims();
    let n = l.w.dims()[1];
    let add = add.map(|a| a.reshape([b * len, n]));
    product_epilogue(
        operand(x.reshape([b * len, inner]), p),
        operand(l.w.clone(), p),
        (Some(l.b.clone()), add),
        format,
        k,
    )
    .reshape([b, len, n])
}

/// Gradients of a linear layer's input (in `dx`), weight and bias (as `matmul.rs`'s operation computes
/// them); with `add` (f32, the input's shape), the input's gradient is that plus the layer's, summed by the
/// product's epilogue (`dx` must then be f32).
pub fn linear_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    dy: Tensor<I, 3>,
    (p, dx): (Precision, FloatDType),
    add: Option<Tensor<I, 3>>,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 2>, Tensor<I, 1>) {
    let [b, len, _] = x.dims();
    let n = dy.dims()[2];
    // The bias's sum and the products' bf16 operand in one pass (as `rows::add_for`), where a cast and
    // then the sum read `dy` twice.
    let (dy2, db) = crate::rows::sum_cast(dy.reshape([b * len, n]), p.operand_dtype());
    let (dx, dw) = product_grad(x, l, dy2, (p, dx), add, k);
    (dx, dw, db)
}

/// Gradients of a product's input (in `dx`, plus `add` where given) and weight from its output's gradient
/// `dy` `[b · l, n]`.
pub fn product_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    dy: Tensor<I, 2>,
    (p, dx): (Precision, FloatDType),
    add: Option<Tensor<I, 3>>,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 2>) {
    let [b, len, inner] = x.dims();
    let dy = operand(dy, p);
    let wt = operand(l.w.clone(), p).transpose();
    let dx = match add {
        Some(a) => {
            let a = a.reshape([b * len, inner]);
            product_epilogue(dy.clone(), wt, (None, Some(a)), dx, k)
        }
        None => product_in(dy.clone(), wt, dx, k),
    };
    let dw = product(operand(x.reshape([b * len, inner]), p).transpose(), dy, k);
    (dx.reshape([b, len, inner]), dw)
}
