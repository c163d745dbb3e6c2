//! The pre-norm cross-attention layer of the ego module: queries over a context of their own.

use crate::layers::{LayerSizes, Mlp, MultiHead, layer_parts};
use burn::module::Module;
use burn::nn::{LayerNorm, LayerNormConfig, Linear};
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, Tensor};
use umgen_ops::layer::{LayerParts, cross_op_for};
use umgen_ops::norm::layer_norm_operand;
use umgen_ops::{KeptInputs, Kernels};

/// A pre-norm cross-attention layer: `x + attn(ln(x), ln(ctx))`, then `x + mlp(ln(x))`.
#[derive(Module, Debug)]
pub struct CrossBlock<B: Backend> {
    ln_q: LayerNorm<B>,
    ln_ctx: LayerNorm<B>,
    attn: MultiHead<B>,
    ln2: LayerNorm<B>,
    mlp: Mlp<B>,
}

impl<B: Backend> CrossBlock<B> {
    /// A layer of `sizes`.
    pub fn new(sizes: LayerSizes, dev: &B::Device) -> Self {
        Self {
            ln_q: LayerNormConfig::new(sizes.d).init(dev),
            ln_ctx: LayerNormConfig::new(sizes.d).init(dev),
            attn: sizes.attention(dev),
            ln2: LayerNormConfig::new(sizes.d).init(dev),
            mlp: sizes.mlp(dev),
        }
    }

    /// The queries' and the context's norms, the attention, the MLP's norm and its two layers.
    #[allow(clippy::type_complexity)]
    pub(crate) fn parts(
        &self,
    ) -> (
        &LayerNorm<B>,
        &LayerNorm<B>,
        &MultiHead<B>,
        &LayerNorm<B>,
        (&Linear<B>, &Linear<B>),
    ) {
        (
            &self.ln_q,
            &self.ln_ctx,
            &self.attn,
            &self.ln2,
            (&self.mlp.fc, &self.mlp.proj),
        )
    }

    /// The layer's parts, for the layer's one operation.
    fn op_parts(&self) -> LayerParts<'_, B> {
        layer_parts(&self.ln_q, Some(&self.ln_ctx), &self.attn, &self.ln2, &self.mlp)
    }

    /// Queries `x` `[b, lq, d]` over `ctx` `[b, lk, d]` with an optional mask (true = hidden), with the
    /// kernels `k`. With recomputation on (`k.recompute`) or `k.layer = fused`, a training backend runs a
    /// layer without a mask as one operation (`umgen_ops::layer`), which keeps only `x` and `ctx` (which
    /// every layer of a stack shares) for the backward pass, or the activations it reads.
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        ctx: Tensor<B, 3>,
        mask: Option<Tensor<B, 4, Bool>>,
        k: &Kernels,
    ) -> Tensor<B, 3> {
        if mask.is_none()
            && let Some(layer) = cross_op_for::<B>(k)
        {
            match layer(&self.op_parts(), x, ctx, k) {
                Ok(y) => return y,
                Err((x, ctx)) => return self.forward_autodiff(x, ctx, None, k),
            }
        }
        self.forward_autodiff(x, ctx, mask, k)
    }

    /// [`Self::forward`] through burn's operations (and their autodiff, on training backends).
    pub(crate) fn forward_autodiff(
        &self,
        x: Tensor<B, 3>,
        ctx: Tensor<B, 3>,
        mask: Option<Tensor<B, 4, Bool>>,
        k: &Kernels,
    ) -> Tensor<B, 3> {
        // Every layer of a stack reads the same context: its norm keeps that tensor as it is rather than a
        // copy of it in the products' format per layer (`kept_inputs`).
        let kc = Kernels {
            kept_inputs: KeptInputs::F32,
            ..*k
        };
        let x = self.attn.forward_onto(
            Some(x.clone()),
            layer_norm_operand(&self.ln_q, x, self.attn.precision, k),
            layer_norm_operand(&self.ln_ctx, ctx, self.attn.precision, &kc),
            mask,
            false,
            k,
        );
        self.mlp.forward_onto(
            x.clone(),
            layer_norm_operand(&self.ln2, x, self.mlp.precision, k),
            k,
        )
    }
}

#[cfg(test)]
mod tests;
