//! The pieces both passes of a recomputed layer are built from: layer norms, linear layers and dropout,
//! each with its gradient, on the same kernels and with the same casts as the autodiff path.

use crate::flash::FusedAttention;
use crate::format::Precision;
use crate::format::operand;
use crate::gelu::FusedGelu;
use crate::kernels::Kernels;
use crate::matmul::{NamedMatmul, product, product_in};
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

/// Gradients of a layer norm's input, scale and shift from its output's gradient `dy`.
pub fn norm_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    (mean, rstd): Stats<I>,
    n: &Norm<I>,
    dy: Tensor<I, 3>,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 1>, Tensor<I, 1>) {
    let [b, l, d] = x.dims();
    let flat = |t: Tensor<I, 3>| t.reshape([b * l, d]);
    let (dx, dgamma, dbeta) = I::norm_backward(flat(dy), flat(x), mean, rstd, n.gamma.clone(), k);
    (dx.reshape([b, l, d]), dgamma, dbeta)
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

/// [`linear`] written in `format` (as `precision::linear_in`): the product, then the bias added in it.
pub fn linear_in<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    p: Precision,
    format: FloatDType,
    k: &Kernels,
) -> Tensor<I, 3> {
    let [b, len, _] = x.dims();
    let n = l.w.dims()[1];
    unbiased(x, l, p, format, k).reshape([b, len, n]) + l.b.clone().cast(format).unsqueeze::<3>()
}

/// Gradients of a linear layer's input (in `dx`), weight and bias (as `matmul.rs`'s operation computes
/// them).
pub fn linear_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    dy: Tensor<I, 3>,
    p: Precision,
    dx: FloatDType,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 2>, Tensor<I, 1>) {
    let [b, len, _] = x.dims();
    let n = dy.dims()[2];
    // The bias's sum and the products' bf16 operand in one pass (as `rows::add_for`), where a cast and
    // then the sum read `dy` twice.
    let (dy2, db) = crate::rows::sum_cast(dy.reshape([b * len, n]), p.operand_dtype());
    let (dx, dw) = product_grad(x, l, dy2, p, dx, k);
    (dx, dw, db)
}

/// Gradients of a product's input (in `dx`) and weight from its output's gradient `dy` `[b · l, n]`.
pub fn product_grad<I: LayerBackend>(
    x: Tensor<I, 3>,
    l: &Lin<I>,
    dy: Tensor<I, 2>,
    p: Precision,
    dx: FloatDType,
    k: &Kernels,
) -> (Tensor<I, 3>, Tensor<I, 2>) {
    let [b, len, inner] = x.dims();
    let dy = operand(dy, p);
    let dx = product_in(dy.clone(), operand(l.w.clone(), p).transpose(), dx, k).reshape([b, len, inner]);
    let dw = product(operand(x.reshape([b * len, inner]), p).transpose(), dy, k);
    (dx, dw)
}
