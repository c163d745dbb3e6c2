//! Mixed precision: matrix products in bf16, everything else in f32.
//!
//! burn 0.21 has no autocast, and a bf16 backend (`Cuda<bf16>`) would make the parameters, their gradients
//! and AdamW's moments bf16 too. With `backbone.precision = "bf16"` the parameters stay f32 (master
//! weights) and only the operands of each linear layer and attention product are cast to bf16; the product
//! is cast back to f32. burn's cast is differentiable, so the gradients reaching the parameters are f32 and
//! the optimizer never sees bf16. Layer norms, softmax statistics, the residual stream and the losses stay
//! f32: what PyTorch's bf16 autocast does for the same operations.

use crate::config::Precision;
use crate::matmul::Written;
use burn::nn::Linear;
use burn::tensor::backend::Backend;
use burn::tensor::{DType, FloatDType, Tensor};

/// `x` in the format products are computed in: bf16 for [`Precision::Bf16`] and
/// [`Precision::Bf16Linear`] (whose attention calls get [`Precision::attention`]'s f32), unchanged for f32.
pub fn operand<B: Backend, const D: usize>(x: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
    x.cast(p.operand_dtype())
}

/// The float format of a float tensor's `dtype` (f32 for a quantized one, which no product here writes).
pub(crate) fn float_format(dtype: DType) -> FloatDType {
    match dtype {
        DType::F64 => FloatDType::F64,
        DType::F16 => FloatDType::F16,
        DType::BF16 => FloatDType::BF16,
        DType::Flex32 => FloatDType::Flex32,
        _ => FloatDType::F32,
    }
}

/// A product's result back in f32 (a no-op for f32 operands).
fn widen<B: Backend, const D: usize>(x: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
    match p {
        Precision::F32 => x,
        Precision::Bf16 | Precision::Bf16Linear => x.cast(FloatDType::F32),
    }
}

/// `a · b` with both operands in `p`'s format, the result in f32. Operands already cast by [`operand`]
/// are not cast again.
pub fn matmul<B: Backend, const D: usize>(a: Tensor<B, D>, b: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
    widen(operand(a, p).matmul(operand(b, p)), p)
}

/// `x · w` over the last axis of `x` as one `[m, k] × [k, n]` product by `product` (the named kernel, over
/// all leading dimensions at once), written in the `written` formats: the `[m, n]` rows, and the
/// dimensions they take back (`x`'s, the last one `n`).
pub(crate) fn product_rows<B: Backend, const D: usize>(
    product: crate::matmul::ProductFn<B>,
    x: Tensor<B, D>,
    w: Tensor<B, 2>,
    p: Precision,
    written: Written,
) -> (Tensor<B, 2>, [usize; D]) {
    let mut dims = x.dims();
    let k = dims[D - 1];
    dims[D - 1] = w.dims()[1];
    (product(x.reshape([-1, k as i32]), w, p, written), dims)
}

/// `layer.forward(x)` with the product in `p`'s format; the bias is added in f32 ([`crate::rows::add`]). Training on CUDA runs the
/// product on the named kernel (`matmul.rs`), as one `[m, k] × [k, n]` product over all leading dimensions.
pub fn linear<B: Backend, const D: usize>(layer: &Linear<B>, x: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
    linear_with(layer, x, p, FloatDType::F32)
}

/// `layer.forward(x)` in `format`, the format its consumer reads (bf16 attention operands): on the named
/// kernel the product is written in it and the bias added in it, where [`linear`] writes f32 and the
/// consumer casts (three passes over the result instead of one). The gradient comes back in any format.
pub fn linear_in<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    format: FloatDType,
) -> Tensor<B, D> {
    let Some(product) = crate::matmul::named_for::<B>().filter(|_| format != FloatDType::F32) else {
        return linear(layer, x, p).cast(format);
    };
    let written = Written {
        out: format,
        dx: FloatDType::F32,
    };
    let (y, dims) = product_rows(product, x, layer.weight.val(), p, written);
    let y = y.reshape(dims);
    match &layer.bias {
        Some(bias) => crate::rows::add_for(y, bias.val(), Some(p.operand_dtype())),
        None => y,
    }
}

/// [`linear`] whose input's gradient is written in `dx` where the named kernel computes it: the MLP's
/// second layer (its input's gradient only feeds the bias + GELU kernel's backward pass, which reads bf16)
/// and the attention's output projection (flash2's backward pass reads the output's gradient in bf16).
pub fn linear_with<B: Backend, const D: usize>(
    layer: &Linear<B>,
    x: Tensor<B, D>,
    p: Precision,
    dx: FloatDType,
) -> Tensor<B, D> {
    let w = layer.weight.val();
    let y = match (crate::matmul::named_for::<B>(), p) {
        (Some(product), _) => {
            let written = Written {
                out: FloatDType::F32,
                dx,
            };
            let (y, dims) = product_rows(product, x, w, p, written);
            y.reshape(dims)
        }
        // burn's layer adds the bias inside its product.
        (None, Precision::F32) => return layer.forward(x),
        (None, Precision::Bf16 | Precision::Bf16Linear) => widen(
            burn::tensor::module::linear(operand(x, p), operand(w, p), None),
            p,
        ),
    };
    // The product's backward pass reads its gradient in the operands' format: the bias's sum writes that
    // copy in the same pass (`rows::add_for`).
    match &layer.bias {
        Some(bias) => crate::rows::add_for(y, bias.val(), Some(p.operand_dtype())),
        None => y,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::nn::LinearConfig;
    use burn::tensor::{DType, Distribution};

    type A = Autodiff<Flex>;

    fn rel(a: Tensor<Flex, 3>, b: Tensor<Flex, 3>) -> f32 {
        let scale = b.clone().abs().max().into_scalar();
        (a - b).abs().max().into_scalar() / scale
    }

    #[test]
    fn bf16_linear_is_close_to_f32_and_keeps_f32_gradients() {
        let dev = Default::default();
        let layer = LinearConfig::new(48, 24).init::<A>(&dev);
        let x = Tensor::<A, 3>::random([2, 5, 48], Distribution::Normal(0.0, 1.0), &dev).require_grad();
        let full = linear(&layer, x.clone(), Precision::F32);
        let half = linear(&layer, x.clone(), Precision::Bf16);
        assert_eq!(half.dtype(), DType::F32);
        let err = rel(half.clone().inner(), full.clone().inner());
        // bf16 keeps 8 significant bits: products of 48 terms land near 2⁻⁸ relative, never at zero.
        assert!(err > 1e-5 && err < 2e-2, "relative error {err}");
        let g_half = half.sum().backward();
        let g_full = full.sum().backward();
        let w = layer.weight.val();
        let (gw_half, gw_full) = (w.grad(&g_half).expect("grad"), w.grad(&g_full).expect("grad"));
        assert_eq!(gw_half.dtype(), DType::F32);
        let err = rel(gw_half.unsqueeze(), gw_full.unsqueeze());
        assert!(err < 2e-2, "weight gradient relative error {err}");
        let bias = layer.bias.as_ref().expect("bias").val();
        assert_eq!(bias.grad(&g_half).expect("bias grad").dtype(), DType::F32);
        assert_eq!(x.grad(&g_half).expect("input grad").dtype(), DType::F32);
    }

    #[test]
    fn bf16_linear_casts_linear_layers_and_leaves_attention_in_f32() {
        let dev = Default::default();
        let layer = LinearConfig::new(48, 24).init::<A>(&dev);
        let x = Tensor::<A, 3>::random([2, 5, 48], Distribution::Normal(0.0, 1.0), &dev);
        let half = linear(&layer, x.clone(), Precision::Bf16).inner();
        let mixed = linear(&layer, x, Precision::Bf16Linear).inner();
        assert_eq!(
            rel(mixed, half),
            0.0,
            "linear layers: the same bf16 products as `bf16`"
        );
        // 300 keys take the training attention's tiled operation on the CPU, whose products follow the
        // precision it is given.
        let qkv = |seed: f64| Tensor::<A, 4>::random([1, 2, 300, 16], Distribution::Normal(seed, 1.0), &dev);
        let (q, k, v) = (qkv(0.0), qkv(0.1), qkv(-0.1));
        let att = |p| {
            crate::attention::attend(q.clone(), k.clone(), v.clone(), None, true, p)
                .inner()
                .flatten::<3>(0, 1)
        };
        let (full, bf16, mixed) = (
            att(Precision::F32),
            att(Precision::Bf16),
            att(Precision::Bf16Linear),
        );
        assert_eq!(rel(mixed, full.clone()), 0.0, "attention: f32 products");
        assert!(
            rel(bf16, full) > 1e-5,
            "bf16 attention products differ from f32 ones"
        );
        assert_eq!(Precision::Bf16Linear.attention(), Precision::F32);
        let parsed: Precision = serde_json::from_str(r#""bf16-linear""#).expect("bf16-linear parses");
        assert_eq!(parsed, Precision::Bf16Linear);
    }
}
