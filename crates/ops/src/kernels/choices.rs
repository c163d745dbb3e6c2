//! The values of each kernel choice in [`super::Kernels`], one enum per `[train.kernels]` key.

use burn::tensor::FloatDType;
use serde::{Deserialize, Serialize};

/// Which kernel runs the linear layers' products in training on CUDA (`train.kernels.matmul`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MatmulKernel {
    /// cubek's `specialized_tma_mma`, through [`crate::matmul::named_autodiff`].
    Named,
    /// cuBLAS's `cublasGemmEx`, through [`crate::matmul::named_autodiff`]; products it cannot take, or a machine without
    /// libcublas, fall back to [`MatmulKernel::Named`] (counted in `fallbacks`).
    #[default]
    Cublas,
    /// burn's default kernel, through burn's own autodiff.
    Burn,
}

/// How a training backend runs the attention layers whose activations it keeps (`train.kernels.layer`;
/// with `recompute` every layer runs as [`LayerKernel::Fused`] does, recomputing).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LayerKernel {
    /// burn's autodiff of each of the layer's operations (norms, products, attention, bias + GELU),
    /// each keeping what its own backward pass reads. The default.
    #[default]
    Burn,
    /// The layer as one operation ([`crate::layer`]) that keeps the activations its hand-written
    /// backward pass reads: the gradients that meet on the residual stream and on the normalised input
    /// are summed by the norm's backward kernel and the key-value product's epilogue, and the autodiff
    /// graph holds one node per layer.
    Fused,
}

/// How the additions around the products and layer norms run (`train.kernels.epilogue`): a bias, the
/// residual stream, or another product's result added to a product, and the residual stream's gradient
/// added to a layer norm's input gradient.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EpilogueKernel {
    /// In the kernels that write the result: cuBLASLt's epilogue (with `matmul = "cublas"`), the layer
    /// norm's backward kernel. The default.
    #[default]
    Fused,
    /// As element-wise kernels of their own after the product or the norm (for comparing the two).
    Apart,
}

/// Which kernels run the training attention on CUDA (`train.kernels.attention`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AttentionKernel {
    /// One fused cubecl kernel per pass (forward; key/value gradients; query gradients).
    Fused,
    /// The tiled passes in burn tensor operations (query blocks of `attention_block_mib`).
    Tiled,
    /// FlashAttention-2 in CUDA C (umgen-cuda's `kernels/flash2/flash2.cu`, NVRTC): products and softmax in registers; head
    /// sizes 32 and 64 (others run [`AttentionKernel::Fused`]). The default: about 2× the fused kernels'
    /// speed.
    #[default]
    Flash2,
}

/// How the flash2 kernels compute the attention's backward pass (`train.kernels.attention_backward`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Flash2Backward {
    /// One kernel for the keys' and values' gradients, another for the queries', each recomputing the
    /// probabilities and their gradients.
    #[default]
    TwoPass,
    /// One kernel for all three: the key/value kernel adds each step's share of the queries' gradient into
    /// an f32 accumulator, as FlashAttention-2's backward pass does (by the TMA unit's bulk reduction, as
    /// FlashAttention-3 adds it). Head size 64 on
    /// Hopper's `wgmma` (compute capability 9.0) only, on cubecl's stream; elsewhere the two-pass kernels
    /// run (counted in the attention's fallbacks).
    OnePass,
}

/// The format the backward pass keeps layer norms' inputs in (`train.kernels.kept_inputs`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KeptInputs {
    /// The products' format (bf16 under the bf16 presets): a layer norm's backward pass is the only reader
    /// of its input, and what the norm feeds the products is rounded to that format anyway. The default.
    #[default]
    Operand,
    /// f32, the residual stream's own format.
    F32,
}

impl KeptInputs {
    /// The format an input is kept in whose layer norm feeds products in `operand` (f32 where the norm's
    /// output is f32: nothing rounds it).
    pub fn format(self, operand: FloatDType) -> FloatDType {
        match self {
            Self::Operand => operand,
            Self::F32 => FloatDType::F32,
        }
    }
}

/// What computes the training layer norms on CUDA (`train.kernels.norm`); the CPU always runs the decomposition.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormKernel {
    /// One CUDA C kernel per pass (umgen-cuda's `kernels/train/norm.cu`). The default.
    #[default]
    Fused,
    /// burn's decomposition (for comparing the kernels with it).
    Burn,
}

/// What computes the MLPs' bias + GELU when training (`train.kernels.gelu`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GeluKernel {
    /// One operation per pass (`gelu::FusedGelu`: on CUDA one CUDA C kernel, umgen-cuda's `kernels/train/gelu.cu`). The default.
    #[default]
    Fused,
    /// burn's bias add and GELU (for comparing the kernels with them).
    Burn,
}

/// What computes the cross-entropy's passes over the logits when training on CUDA (`train.kernels.xent`); the
/// CPU always runs burn's operations.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum XentKernel {
    /// One CUDA C kernel per pass (umgen-cuda's `kernels/train/xent.cu`). The default.
    #[default]
    Fused,
    /// burn's operations (for comparing the kernels with them).
    Burn,
}

/// What steps AdamW when training on CUDA (`train.kernels.adamw`); the CPU always steps tensor by tensor.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AdamWChoice {
    /// One CUDA C kernel for all parameter tensors (umgen-cuda's `kernels/train/adamw.cu`). The default.
    #[default]
    Fused,
    /// burn's AdamW, one chain of tensor operations per parameter tensor (for comparing the kernel with it).
    Burn,
}

/// Where the CUDA C kernels and cuBLAS's products run (`train.kernels.stream`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KernelStream {
    /// cubecl's own stream, launched as cubecl kernels. The default.
    #[default]
    Cubecl,
    /// A side stream per kernel family, ordered with cubecl's through device flags (for comparing the
    /// two).
    Side,
}

/// Which thread launches umgen's custom operations' work (`train.kernels.launch_thread`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LaunchThread {
    /// cubecl's device thread, one blocking call per operation. The default.
    #[default]
    Device,
    /// The calling thread, a blocking call per device pointer (for comparing the two).
    Caller,
}
