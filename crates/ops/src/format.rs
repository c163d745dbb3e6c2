//! Number formats: the products' format ([`Precision`]), casts to and from it, and float primitives as
//! tensors.
//!
//! burn 0.21 has no autocast, and a bf16 backend (`Cuda<bf16>`) would make the parameters, their gradients
//! and AdamW's moments bf16 too. With `backbone.precision = "bf16"` the parameters stay f32 (master
//! weights) and only the operands of each linear layer and attention product are cast to bf16; the product
//! is cast back to f32. burn's cast is differentiable, so the gradients reaching the parameters are f32 and
//! the optimizer never sees bf16. Layer norms, softmax statistics, the residual stream and the losses stay
//! f32: what PyTorch's bf16 autocast does for the same operations.

use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, FloatDType, Tensor, TensorPrimitive};
use serde::{Deserialize, Serialize};

/// Number format of the backbone's matrix products.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Everything in f32 (TF32 on CUDA tensor cores).
    #[default]
    F32,
    /// Linear layers and attention products in bf16 with f32 accumulation and f32 outputs; parameters,
    /// gradients, optimizer state, norms, softmax statistics and losses stay f32.
    Bf16,
    /// Linear layers and output heads as [`Precision::Bf16`], the attention's products in f32: on CUDA the
    /// fused attention kernels are faster on f32 operands than on bf16 ones (docs/decisions/006-products-on-cublas-in-bf16.md), the named
    /// matmul kernel is faster on bf16 ones.
    #[serde(rename = "bf16-linear")]
    Bf16Linear,
}

impl Precision {
    /// The format of the attention's products (the linear layers around it keep `self`).
    pub fn attention(self) -> Precision {
        match self {
            Precision::Bf16Linear => Precision::F32,
            p => p,
        }
    }

    /// The format the linear layers' operands are cast to (`precision::operand`): bf16 for
    /// [`Precision::Bf16`] and [`Precision::Bf16Linear`], f32 for [`Precision::F32`].
    pub fn operand_dtype(self) -> FloatDType {
        match self {
            Precision::F32 => FloatDType::F32,
            Precision::Bf16 | Precision::Bf16Linear => FloatDType::BF16,
        }
    }
}

/// `x` in the format products are computed in: bf16 for [`Precision::Bf16`] and
/// [`Precision::Bf16Linear`] (whose attention calls get [`Precision::attention`]'s f32), unchanged for f32.
pub fn operand<B: Backend, const D: usize>(x: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
    x.cast(p.operand_dtype())
}

/// The float format of a float tensor's `dtype` (f32 for a quantized one, which no product here writes).
pub fn float_format(dtype: DType) -> FloatDType {
    match dtype {
        DType::F64 => FloatDType::F64,
        DType::F16 => FloatDType::F16,
        DType::BF16 => FloatDType::BF16,
        DType::Flex32 => FloatDType::Flex32,
        _ => FloatDType::F32,
    }
}

/// A product's result back in f32 (a no-op for f32 operands).
pub(crate) fn widen<B: Backend, const D: usize>(x: Tensor<B, D>, p: Precision) -> Tensor<B, D> {
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

/// A float primitive as a tensor of rank `D`.
pub fn float<B: Backend, const D: usize>(t: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}
