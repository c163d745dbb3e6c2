//! Output heads with per-modality vocabularies, and the cross-entropy over them.

use crate::config::Precision;
use crate::spec::SegmentSpec;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};
use umgen_ops::Kernels;
use umgen_ops::linear::linear;

/// One bias-free linear head per segment, over that segment's content ids only: a position's logits never
/// cover another modality's ids.
#[derive(Module, Debug)]
pub struct Heads<B: Backend> {
    heads: Vec<Linear<B>>,
    content: Vec<[usize; 2]>,
    precision: Precision,
}

impl<B: Backend> Heads<B> {
    /// Heads for `segments` from width `d`, their products in `precision` (logits are f32 either way);
    /// the first `ordinal[s]` columns of segment `s`'s head start as a sinusoid ([`crate::ordinal`];
    /// none past the slice's end).
    pub fn new(
        segments: &[SegmentSpec],
        d: usize,
        precision: Precision,
        ordinal: &[usize],
        dev: &B::Device,
    ) -> Self {
        Self {
            heads: segments
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    let head = LinearConfig::new(d, s.vocab).with_bias(false).init(dev);
                    crate::ordinal::head(head, ordinal.get(i).copied().unwrap_or(0))
                })
                .collect(),
            content: segments.iter().map(|s| [s.offset, s.tokens]).collect(),
            precision,
        }
    }

    /// Each segment's head.
    pub(crate) fn linears(&self) -> &[Linear<B>] {
        &self.heads
    }

    /// Logits `[m, tokens, vocab]` of segment `s` from features `[m, N, d]`, with the kernels `k`.
    pub fn logits(&self, s: usize, x: Tensor<B, 3>, k: &Kernels) -> Tensor<B, 3> {
        let [offset, tokens] = self.content[s];
        linear(&self.heads[s], x.narrow(1, offset, tokens), self.precision, k)
    }

    /// Logits of one position `p` of segment `s` from features `[m, d]`: `[m, vocab]`.
    pub fn logits_at(&self, s: usize, x: Tensor<B, 2>) -> Tensor<B, 2> {
        linear(&self.heads[s], x, self.precision, &Kernels::DEFAULT)
    }

    /// Summed cross-entropy per segment of features `[m, N, d]` against targets `[m, N]`, with the number
    /// of tokens each sum covers. Segment `s`'s first `ordinal[s]` ids are ordered bins, scored with
    /// `umgen_ops::smoothing::nll_sum` at `sigma` bins (0: plain cross-entropy), through
    /// one fused operation on the training backends (`xent.rs`).
    pub fn cross_entropy(
        &self,
        x: Tensor<B, 3>,
        targets: Tensor<B, 2, Int>,
        ordinal: &[usize],
        sigma: f64,
        k: &Kernels,
    ) -> Vec<(Tensor<B, 1>, usize)> {
        let m = x.dims()[0];
        (0..self.heads.len())
            .map(|s| {
                let [offset, tokens] = self.content[s];
                let logits = self.logits(s, x.clone(), k);
                let v = logits.dims()[2];
                let t = targets.clone().narrow(1, offset, tokens).reshape([m * tokens, 1]);
                let ord = ordinal.get(s).copied().unwrap_or(0);
                let sum = umgen_ops::xent::sum(logits.reshape([m * tokens, v]), t, ord, sigma, k);
                (sum, m * tokens)
            })
            .collect()
    }
}
