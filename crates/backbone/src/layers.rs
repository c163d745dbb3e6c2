//! Transformer layers: pre-norm self-attention blocks with GELU MLPs, and the attention and MLP that
//! `crate::cross`'s cross-attention blocks share.

use crate::config::Precision;
use burn::module::Module;
use burn::nn::{Dropout, DropoutConfig, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::activation::softmax;
use burn::tensor::backend::Backend;
use burn::tensor::{Bool, FloatDType, Tensor};
use umgen_ops::Kernels;
use umgen_ops::format::float_format;
use umgen_ops::heads::{merge_heads, split_heads};
use umgen_ops::layer::{LayerParts, layer_op_for};
use umgen_ops::linear::{linear, linear_in, linear_residual, linear_with};
use umgen_ops::mlp::{gelu_mlp, gelu_mlp_onto};
use umgen_ops::norm::layer_norm_operand;

/// `Linear(d → r·d), GELU, Linear(r·d → d)`, dropout on the output.
#[derive(Module, Debug)]
pub struct Mlp<B: Backend> {
    pub(crate) fc: Linear<B>,
    pub(crate) proj: Linear<B>,
    drop: Dropout,
    pub(crate) precision: Precision,
}

impl<B: Backend> Mlp<B> {
    /// An MLP of width `d` and hidden width `hidden`, its products in `precision`.
    pub fn new(d: usize, hidden: usize, dropout: f64, precision: Precision, dev: &B::Device) -> Self {
        Self {
            fc: LinearConfig::new(d, hidden).init(dev),
            proj: LinearConfig::new(hidden, d).init(dev),
            drop: DropoutConfig::new(dropout).init(),
            precision,
        }
    }

    /// Applies it with the kernels `k`.
    pub fn forward<const D: usize>(&self, x: Tensor<B, D>, k: &Kernels) -> Tensor<B, D> {
        let p = self.precision;
        self.drop.forward(gelu_mlp(&self.fc, &self.proj, x, p, k))
    }

    /// `residual + self.forward(x)`: without dropout, the second product's epilogue adds the residual
    /// stream.
    pub fn forward_onto<const D: usize>(
        &self,
        residual: Tensor<B, D>,
        x: Tensor<B, D>,
        k: &Kernels,
    ) -> Tensor<B, D> {
        if self.drop.prob == 0.0 {
            gelu_mlp_onto(Some(residual), &self.fc, &self.proj, x, self.precision, k)
        } else {
            residual + self.forward(x, k)
        }
    }
}

/// Multi-head attention of queries over keys and values (self- or cross-attention), through burn's
/// attention operation (fused on backends that have a kernel).
#[derive(Module, Debug)]
pub struct MultiHead<B: Backend> {
    q: Linear<B>,
    kv: Linear<B>,
    proj: Linear<B>,
    drop: Dropout,
    heads: usize,
    pub(crate) precision: Precision,
}

impl<B: Backend> MultiHead<B> {
    /// Attention of width `d` with `heads` heads, its products in `precision`.
    pub fn new(d: usize, heads: usize, dropout: f64, precision: Precision, dev: &B::Device) -> Self {
        Self {
            q: LinearConfig::new(d, d).init(dev),
            kv: LinearConfig::new(d, 2 * d).init(dev),
            proj: LinearConfig::new(d, d).init(dev),
            drop: DropoutConfig::new(dropout).init(),
            heads,
            precision,
        }
    }

    /// Queries `x` `[b, lq, d]` over `ctx` `[b, lk, d]`; `mask` `[b, heads, lq, lk]` (true = hidden);
    /// `causal` hides later positions (bottom-right aligned).
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        ctx: Tensor<B, 3>,
        mask: Option<Tensor<B, 4, Bool>>,
        causal: bool,
        k: &Kernels,
    ) -> Tensor<B, 3> {
        self.forward_onto(None, x, ctx, mask, causal, k)
    }

    /// [`Self::forward`] added to `residual` `[b, lq, d]` where given (a pre-norm layer's residual stream):
    /// on the training backends the output projection's epilogue adds it.
    pub fn forward_onto(
        &self,
        residual: Option<Tensor<B, 3>>,
        x: Tensor<B, 3>,
        ctx: Tensor<B, 3>,
        mask: Option<Tensor<B, 4, Bool>>,
        causal: bool,
        k: &Kernels,
    ) -> Tensor<B, 3> {
        let p = self.precision;
        // The queries straight in the attention's format where one operation takes them (that operation
        // casts them otherwise, after the bias add's pass). Not the keys and values: the operation splits
        // them with views, which burn-fusion copies from a tensor that needs no cast (24 copies, 2.6 ms
        // of a `small` step) but reads strided inside the cast of an f32 one.
        let (lq, lk) = (x.dims()[1], ctx.dims()[1]);
        let format = if umgen_ops::attention::attends_kv_in_one::<B>(mask.is_none(), lq, lk, causal) {
            p.attention().operand_dtype()
        } else {
            FloatDType::F32
        };
        let q = split_heads(linear_in(&self.q, x, p, format, k), self.heads);
        let kv = linear(&self.kv, ctx, p, k);
        let y = merge_heads(umgen_ops::attention::attend_kv(q, kv, mask, causal, p, k));
        self.output_onto(residual, y, k)
    }

    /// Queries of `x` and keys and values of `ctx`, split into heads `[b, heads, l, dh]` (decoding: the
    /// kernels' choices are the training backends', which decoding does not run on).
    fn project(&self, x: Tensor<B, 3>, ctx: Tensor<B, 3>) -> (Tensor<B, 4>, Tensor<B, 4>, Tensor<B, 4>) {
        let (p, k) = (self.precision, &Kernels::DEFAULT);
        let q = split_heads(linear(&self.q, x, p, k), self.heads);
        let (keys, values) = umgen_ops::heads::split_kv(linear(&self.kv, ctx, p, k), self.heads);
        (q, keys, values)
    }

    /// Heads merged, projected back to width d, dropout.
    fn output(&self, y: Tensor<B, 4>, k: &Kernels) -> Tensor<B, 3> {
        self.output_onto(None, merge_heads(y), k)
    }

    /// Merged heads `[b, l, d]` projected back to width d, dropout, added to `residual` where given
    /// (without dropout, by the projection's epilogue). The heads' gradient comes back in their own format:
    /// bf16 where the flash2 kernels wrote them so, which their backward pass reads as it is.
    fn output_onto(&self, residual: Option<Tensor<B, 3>>, y: Tensor<B, 3>, k: &Kernels) -> Tensor<B, 3> {
        let dx = float_format(y.dtype());
        let p = self.precision;
        match residual {
            Some(r) if self.drop.prob == 0.0 => linear_residual(&self.proj, y, r, p, dx, k),
            Some(r) => r + self.drop.forward(linear_with(&self.proj, y, p, dx, k)),
            None => self.drop.forward(linear_with(&self.proj, y, p, dx, k)),
        }
    }

    /// Attention over time of `x` `[b, t, n, d]` (each position over its own frames, `causal`) by `op`, the
    /// training backends' [`crate::temporal`] operation: the products run on the rows as they lie.
    fn over_time(
        &self,
        residual: Tensor<B, 4>,
        x: Tensor<B, 4>,
        op: umgen_ops::temporal::OverTime<B>,
        k: &Kernels,
    ) -> Tensor<B, 4> {
        let [b, t, n, d] = x.dims();
        let p = self.precision;
        // Cast once for both products (each would cast its own copy).
        let rows = umgen_ops::format::operand(x.reshape([b, t * n, d]), p);
        let q = linear(&self.q, rows.clone(), p, k).reshape([b, t, n, d]);
        let kv = linear(&self.kv, rows, p, k).reshape([b, t, n, 2 * d]);
        let y = op(q, kv, self.heads, true, p, k);
        let residual = Some(residual.reshape([b, t * n, d]));
        self.output_onto(residual, y.reshape([b, t * n, d]), k)
            .reshape([b, t, n, d])
    }

    /// Heads.
    pub fn heads(&self) -> usize {
        self.heads
    }

    /// The query, key-and-value and output projections.
    pub(crate) fn linears(&self) -> (&Linear<B>, &Linear<B>, &Linear<B>) {
        (&self.q, &self.kv, &self.proj)
    }

    /// Self-attention of the newest position `x` `[m, 1, d]`, written at position `pos` of `cache` (keys and
    /// values `[m, heads, capacity, dh]`, allocated at full size on the first step), over itself and the
    /// positions before it; `hidden` `[1, 1, 1, capacity]` is 0 where a key may be seen and a large negative
    /// number past `pos`. Every step thus has the same shapes: a cache that grew by one position per step
    /// gave each step new shapes, which on CUDA can mean new kernels to compile or tune, and a copy of the
    /// whole cache per step.
    pub(crate) fn forward_step(
        &self,
        x: Tensor<B, 3>,
        cache: &mut Option<(Tensor<B, 4>, Tensor<B, 4>)>,
        pos: usize,
        hidden: Tensor<B, 4>,
    ) -> Tensor<B, 3> {
        let (q, k, v) = self.project(x.clone(), x);
        let [m, h, _, dh] = k.dims();
        let capacity = hidden.dims()[3];
        let (k0, v0) = cache.take().unwrap_or_else(|| {
            let dev = k.device();
            (
                Tensor::zeros([m, h, capacity, dh], &dev),
                Tensor::zeros([m, h, capacity, dh], &dev),
            )
        });
        let at = [0..m, 0..h, pos..pos + q.dims()[2], 0..dh];
        let (k, v) = (k0.slice_assign(at.clone(), k), v0.slice_assign(at, v));
        *cache = Some((k.clone(), v.clone()));
        let scores = q.matmul(k.swap_dims(2, 3)).mul_scalar((dh as f64).sqrt().recip()) + hidden;
        self.output(softmax(scores, 3).matmul(v), &Kernels::DEFAULT)
    }
}

/// What sizes one transformer layer: width, heads, MLP ratio, dropout and the precision of its products.
#[derive(Debug, Clone, Copy)]
pub struct LayerSizes {
    /// Width d.
    pub d: usize,
    /// Attention heads.
    pub heads: usize,
    /// MLP hidden width as a multiple of d.
    pub ratio: usize,
    /// Dropout on the attention and MLP outputs.
    pub dropout: f64,
    /// Number format of the products.
    pub precision: Precision,
}

impl LayerSizes {
    pub(crate) fn attention<B: Backend>(&self, dev: &B::Device) -> MultiHead<B> {
        MultiHead::new(self.d, self.heads, self.dropout, self.precision, dev)
    }

    pub(crate) fn mlp<B: Backend>(&self, dev: &B::Device) -> Mlp<B> {
        Mlp::new(self.d, self.ratio * self.d, self.dropout, self.precision, dev)
    }
}

/// A pre-norm self-attention layer: `x + attn(ln(x))`, then `x + mlp(ln(x))`.
#[derive(Module, Debug)]
pub struct SelfBlock<B: Backend> {
    ln1: LayerNorm<B>,
    attn: MultiHead<B>,
    ln2: LayerNorm<B>,
    mlp: Mlp<B>,
}

impl<B: Backend> SelfBlock<B> {
    /// A layer of `sizes`.
    pub fn new(sizes: LayerSizes, dev: &B::Device) -> Self {
        Self {
            ln1: LayerNormConfig::new(sizes.d).init(dev),
            attn: sizes.attention(dev),
            ln2: LayerNormConfig::new(sizes.d).init(dev),
            mlp: sizes.mlp(dev),
        }
    }

    /// Applies it to `[b, l, d]`; `causal` lets position `i` see positions `≤ i` only. With recomputation on
    /// (`k.recompute`) or `k.layer = fused`, a training backend runs it as one operation
    /// (`umgen_ops::layer`), which keeps only `x` for the backward pass or the activations it reads.
    pub fn forward(&self, x: Tensor<B, 3>, causal: bool, k: &Kernels) -> Tensor<B, 3> {
        match layer_op_for::<B>(k) {
            Some(layer) => layer(&self.parts(), x, causal, None, k)
                .unwrap_or_else(|x| self.forward_autodiff(x, causal, k)),
            None => self.forward_autodiff(x, causal, k),
        }
    }

    /// The causal layer over time of `x` `[b, t, n, d]`: each of the `n` positions attends over its own
    /// `t` frames. Training backends run `umgen_ops::temporal`'s operation on the rows as they lie, inside
    /// the layer's one operation (`umgen_ops::layer`) or not; the others group the frames of each
    /// position (`[b · n, t, d]`, a transposition each way) for `forward_autodiff`.
    pub fn forward_over_time(&self, x: Tensor<B, 4>, k: &Kernels) -> Tensor<B, 4> {
        let [b, t, n, d] = x.dims();
        match layer_op_for::<B>(k) {
            Some(layer) => match layer(&self.parts(), x.reshape([b, t * n, d]), true, Some((t, n)), k) {
                Ok(y) => y.reshape([b, t, n, d]),
                Err(x) => self.over_time_autodiff(x.reshape([b, t, n, d]), k),
            },
            None => self.over_time_autodiff(x, k),
        }
    }

    /// [`Self::forward_over_time`] through burn's autodiff (and [`crate::temporal`]'s operation where the
    /// backend has it).
    pub(crate) fn over_time_autodiff(&self, x: Tensor<B, 4>, k: &Kernels) -> Tensor<B, 4> {
        let [b, t, n, d] = x.dims();
        match umgen_ops::temporal::over_time_for::<B>() {
            Some(op) => {
                let n1 = layer_norm_operand(&self.ln1, x.clone(), self.attn.precision, k);
                let x = self.attn.over_time(x, n1, op, k);
                self.mlp.forward_onto(
                    x.clone(),
                    layer_norm_operand(&self.ln2, x, self.mlp.precision, k),
                    k,
                )
            }
            None => self
                .forward_autodiff(x.swap_dims(1, 2).reshape([b * n, t, d]), true, k)
                .reshape([b, n, t, d])
                .swap_dims(1, 2),
        }
    }

    /// [`Self::forward`] through burn's operations (and their autodiff, on training backends).
    pub(crate) fn forward_autodiff(&self, x: Tensor<B, 3>, causal: bool, k: &Kernels) -> Tensor<B, 3> {
        // In the products' format once for the queries' and the keys' and values' products (each would
        // cast its own copy).
        let n = layer_norm_operand(&self.ln1, x.clone(), self.attn.precision, k);
        let x = self.attn.forward_onto(Some(x), n.clone(), n, None, causal, k);
        self.mlp.forward_onto(
            x.clone(),
            layer_norm_operand(&self.ln2, x, self.mlp.precision, k),
            k,
        )
    }

    /// The causal layer on one new position `[m, 1, d]`, with the keys and values of the earlier ones in
    /// `cache`.
    pub(crate) fn forward_step(
        &self,
        x: Tensor<B, 3>,
        cache: &mut Option<(Tensor<B, 4>, Tensor<B, 4>)>,
        pos: usize,
        hidden: Tensor<B, 4>,
    ) -> Tensor<B, 3> {
        // One position at a time: no long gradient sums to shape, and the CPU backend's fused norm.
        let x = x.clone() + self.attn.forward_step(self.ln1.forward(x), cache, pos, hidden);
        x.clone() + self.mlp.forward(self.ln2.forward(x), &Kernels::DEFAULT)
    }
}

impl<B: Backend> SelfBlock<B> {
    /// The layer's parts, for the layer's one operation.
    pub(crate) fn parts(&self) -> LayerParts<'_, B> {
        layer_parts(&self.ln1, None, &self.attn, &self.ln2, &self.mlp)
    }
}

/// The parts of a pre-norm layer for the layer's one operation: the attention's norm `ln1` (the queries'
/// in a cross-attention layer, whose context has `ln_ctx`), the attention, the MLP's norm and the MLP.
pub(crate) fn layer_parts<'a, B: Backend>(
    ln1: &'a LayerNorm<B>,
    ln_ctx: Option<&'a LayerNorm<B>>,
    attn: &'a MultiHead<B>,
    ln2: &'a LayerNorm<B>,
    mlp: &'a Mlp<B>,
) -> LayerParts<'a, B> {
    LayerParts {
        ln1,
        ln_ctx,
        q: &attn.q,
        kv: &attn.kv,
        proj: &attn.proj,
        ln2,
        fc: &mlp.fc,
        out: &mlp.proj,
        heads: attn.heads,
        precision: attn.precision,
        attn_dropout: attn.drop.prob,
        mlp_dropout: mlp.drop.prob,
    }
}

#[cfg(test)]
mod tests;
