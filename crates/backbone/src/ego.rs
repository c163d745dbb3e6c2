//! Ego-action prediction (paper eq. 4): learned queries attend to the ego history (CA_hist), then to the
//! current environment (CA_env), and predict the next frame's action tokens.

use crate::config::Precision;
use crate::cross::CrossBlock;
use crate::layers::LayerSizes;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, Distribution, Tensor, TensorData};
use umgen_ops::Kernels;
use umgen_ops::linear::linear;

/// The ego module.
#[derive(Module, Debug)]
pub struct EgoModule<B: Backend> {
    queries: Param<Tensor<B, 2>>,
    hist: Vec<CrossBlock<B>>,
    env: Vec<CrossBlock<B>>,
    ln: LayerNorm<B>,
    head: Linear<B>,
    heads: usize,
    block: [usize; 2],
    /// Content position of the action tokens, when each frame's queries start from its own action.
    last: Option<usize>,
    precision: Precision,
}

/// Sizes of an [`EgoModule`].
#[derive(Debug, Clone, Copy)]
pub struct EgoSizes {
    /// Sizes of each cross-attention layer.
    pub layer: LayerSizes,
    /// Add each frame's own action (the motion that led to it) to its queries (`backbone.ego_last`).
    pub last: bool,
    /// CA_hist layers.
    pub hist: usize,
    /// CA_env layers.
    pub env: usize,
}

impl<B: Backend> EgoModule<B> {
    /// A module predicting `queries` tokens of vocabulary `vocab` from the action block `block`
    /// (`[start, len]` positions, boundary tokens included; its content at `offset`); the head's first
    /// `ordinal` ids start as a sinusoid ([`crate::ordinal`]).
    pub fn new(
        s: EgoSizes,
        queries: usize,
        vocab: usize,
        ordinal: usize,
        block: [usize; 2],
        offset: usize,
        dev: &B::Device,
    ) -> Self {
        let blocks = |n: usize| (0..n).map(|_| CrossBlock::new(s.layer, dev)).collect();
        Self {
            queries: Param::from_tensor(Tensor::random(
                [queries, s.layer.d],
                Distribution::Normal(0.0, 0.02),
                dev,
            )),
            hist: blocks(s.hist),
            env: blocks(s.env),
            ln: LayerNormConfig::new(s.layer.d).init(dev),
            head: crate::ordinal::head(
                LinearConfig::new(s.layer.d, vocab).with_bias(false).init(dev),
                ordinal,
            ),
            heads: s.layer.heads,
            block,
            last: s.last.then_some(offset),
            precision: s.layer.precision,
        }
    }

    /// The queries, the CA_hist and CA_env layers, the final norm, the head, the action block and the
    /// content position of each frame's own action (`ego_last`).
    #[allow(clippy::type_complexity)]
    pub(crate) fn parts(
        &self,
    ) -> (
        &Param<Tensor<B, 2>>,
        &[CrossBlock<B>],
        &[CrossBlock<B>],
        &LayerNorm<B>,
        &Linear<B>,
        [usize; 2],
        Option<usize>,
    ) {
        (
            &self.queries,
            &self.hist,
            &self.env,
            &self.ln,
            &self.head,
            self.block,
            self.last,
        )
    }

    /// Logits `[b, t, q, vocab]` of the action tokens of frame `i + 1` from frames `0..=i` of `e`
    /// `[b, t, N, d]`; with `last_only`, only for the last frame (`[b, 1, q, vocab]`); with the kernels `k`.
    pub fn forward(&self, e: Tensor<B, 4>, last_only: bool, k: &Kernels) -> Tensor<B, 4> {
        let [b, t, n, d] = e.dims();
        let [start, len] = self.block;
        let q = self.queries.dims()[0];
        let tq = if last_only { 1 } else { t };
        let hist = e.clone().narrow(2, start, len).reshape([b, t * len, d]);
        let mut x = self
            .queries
            .val()
            .unsqueeze_dim::<3>(0)
            .unsqueeze_dim::<4>(0)
            .expand([b, tq, q, d])
            .reshape([b, tq * q, d]);
        let first = t - tq;
        if let Some(at) = self.last {
            // Frame i's own action: the history's embeddings carry no time, so without it the queries
            // cannot tell the latest motion from older ones, and repeating it (constant velocity) is hard.
            let own = e.clone().narrow(1, first, tq).narrow(2, at, q);
            x = x + own.reshape([b, tq * q, d]);
        }
        // The queries of frame i see the action blocks of frames 0..=i.
        let mask: Vec<bool> = (0..tq * q)
            .flat_map(|r| (0..t * len).map(move |c| c / len > first + r / q))
            .collect();
        let mask = Tensor::<B, 2, Bool>::from_data(TensorData::new(mask, [tq * q, t * len]), &e.device())
            .reshape([1, 1, tq * q, t * len])
            .expand([b, self.heads, tq * q, t * len]);
        for blk in &self.hist {
            x = blk.forward(x, hist.clone(), Some(mask.clone()), k);
        }
        // Then each frame's queries see that frame's environment: every block but the action's.
        let mut parts = Vec::new();
        if start > 0 {
            parts.push(e.clone().narrow(2, 0, start));
        }
        if start + len < n {
            parts.push(e.narrow(2, start + len, n - start - len));
        }
        let env = Tensor::cat(parts, 2).narrow(1, first, tq);
        let env = env.reshape([b * tq, n - len, d]);
        let mut x = x.reshape([b * tq, q, d]);
        for blk in &self.env {
            x = blk.forward(x, env.clone(), None, k);
        }
        let logits = linear(
            &self.head,
            umgen_ops::norm::layer_norm_operand(&self.ln, x, self.precision, k),
            self.precision,
            k,
        );
        let v = logits.dims()[2];
        logits.reshape([b, tq, q, v])
    }
}
