//! The backbone's weights as plain f32 arrays, arranged as the model is: what an inference engine outside
//! burn (`umgen_generate::engine`) builds its buffers from. Linear weights keep burn's layout, `[d_in][d_out]`
//! row-major, with `y = x·W + b`.

use crate::cross::CrossBlock;
use crate::ego::EgoModule;
use crate::embed::FrameEmbedding;
use crate::heads::Heads;
use crate::layers::{MultiHead, SelfBlock};
use crate::model::Backbone;
use crate::spec::BackboneSpec;
use burn::module::Param;
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// A tensor's values in row-major order.
fn values<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

fn param<B: Backend, const D: usize>(p: &Param<Tensor<B, D>>) -> Vec<f32> {
    values(p.val())
}

/// A linear layer: `w` `[d_in][d_out]`, an optional bias `[d_out]`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainLinear {
    /// Weights, row-major `[d_in][d_out]`.
    pub w: Vec<f32>,
    /// Bias.
    pub b: Option<Vec<f32>>,
    /// Input width.
    pub d_in: usize,
    /// Output width.
    pub d_out: usize,
}

impl PlainLinear {
    pub(crate) fn of<B: Backend>(l: &Linear<B>) -> Self {
        let [d_in, d_out] = l.weight.val().dims();
        Self {
            w: param(&l.weight),
            b: l.bias.as_ref().map(param),
            d_in,
            d_out,
        }
    }
}

/// A layer norm's scale and shift (ε = [`umgen_ops::norm::LN_EPS`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PlainNorm {
    /// Scale.
    pub g: Vec<f32>,
    /// Shift (zeros for a norm without one).
    pub b: Vec<f32>,
}

impl PlainNorm {
    pub(crate) fn of<B: Backend>(n: &LayerNorm<B>) -> Self {
        let g = param(&n.gamma);
        let b = n.beta.as_ref().map_or_else(|| vec![0.0; g.len()], param);
        Self { g, b }
    }
}

/// Multi-head attention: queries from `q`, keys and values from `kv` (keys' columns first), output `proj`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainAttention {
    /// Query projection.
    pub q: PlainLinear,
    /// Key and value projection.
    pub kv: PlainLinear,
    /// Output projection.
    pub proj: PlainLinear,
    /// Heads.
    pub heads: usize,
}

impl PlainAttention {
    pub(crate) fn of<B: Backend>(a: &MultiHead<B>) -> Self {
        let (q, kv, proj) = a.linears();
        Self {
            q: PlainLinear::of(q),
            kv: PlainLinear::of(kv),
            proj: PlainLinear::of(proj),
            heads: a.heads(),
        }
    }
}

/// `fc`, GELU, `proj`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainMlp {
    /// First layer.
    pub fc: PlainLinear,
    /// Second layer.
    pub proj: PlainLinear,
}

/// A pre-norm self-attention layer: `x + attn(ln1(x))`, then `x + mlp(ln2(x))`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainSelf {
    /// Attention's norm.
    pub ln1: PlainNorm,
    /// Attention.
    pub attn: PlainAttention,
    /// MLP's norm.
    pub ln2: PlainNorm,
    /// MLP.
    pub mlp: PlainMlp,
}

impl PlainSelf {
    pub(crate) fn of<B: Backend>(b: &SelfBlock<B>) -> Self {
        let p = b.parts();
        Self {
            ln1: PlainNorm::of(p.ln1),
            attn: PlainAttention {
                q: PlainLinear::of(p.q),
                kv: PlainLinear::of(p.kv),
                proj: PlainLinear::of(p.proj),
                heads: p.heads,
            },
            ln2: PlainNorm::of(p.ln2),
            mlp: PlainMlp {
                fc: PlainLinear::of(p.fc),
                proj: PlainLinear::of(p.out),
            },
        }
    }
}

/// A pre-norm cross-attention layer: `x + attn(ln_q(x), ln_ctx(ctx))`, then `x + mlp(ln2(x))`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainCross {
    /// The queries' norm.
    pub ln_q: PlainNorm,
    /// The context's norm.
    pub ln_ctx: PlainNorm,
    /// Attention.
    pub attn: PlainAttention,
    /// MLP's norm.
    pub ln2: PlainNorm,
    /// MLP.
    pub mlp: PlainMlp,
}

impl PlainCross {
    pub(crate) fn of<B: Backend>(c: &CrossBlock<B>) -> Self {
        let (ln_q, ln_ctx, attn, ln2, (fc, proj)) = c.parts();
        Self {
            ln_q: PlainNorm::of(ln_q),
            ln_ctx: PlainNorm::of(ln_ctx),
            attn: PlainAttention::of(attn),
            ln2: PlainNorm::of(ln2),
            mlp: PlainMlp {
                fc: PlainLinear::of(fc),
                proj: PlainLinear::of(proj),
            },
        }
    }
}

/// One segment's embedding table: rows `[embed_vocab][dim]`, projected to the embedding width by `proj`
/// where the segment has a codebook.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainTable {
    /// Rows.
    pub rows: Vec<f32>,
    /// Row width.
    pub dim: usize,
    /// Projection to the embedding width.
    pub proj: Option<PlainLinear>,
}

/// The token embedding: `MLP(table[id] + pos[p])`, MLP = `fc1`, GELU, `fc2`.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainEmbed {
    /// Per segment.
    pub tables: Vec<PlainTable>,
    /// Position embeddings `[N][e]`.
    pub pos: Vec<f32>,
    /// Embedding width.
    pub e: usize,
    /// MLP's first layer (e → d).
    pub fc1: PlainLinear,
    /// MLP's second layer (d → d).
    pub fc2: PlainLinear,
}

/// The ego module (see [`EgoModule`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PlainEgo {
    /// Learned queries `[q][d]`.
    pub queries: Vec<f32>,
    /// Query count (action tokens).
    pub q: usize,
    /// CA_hist layers.
    pub hist: Vec<PlainCross>,
    /// CA_env layers.
    pub env: Vec<PlainCross>,
    /// Final norm.
    pub ln: PlainNorm,
    /// Head (no bias).
    pub head: PlainLinear,
    /// The action block `[start, len]`.
    pub block: [usize; 2],
    /// The action's content position, when each frame's queries start from its own action.
    pub last: Option<usize>,
}

/// Every weight of a [`Backbone`], and its frame spec.
#[derive(Debug, Clone, PartialEq)]
pub struct PlainBackbone {
    /// The frame spec.
    pub spec: BackboneSpec,
    /// Width.
    pub d: usize,
    /// Heads of every attention layer.
    pub heads: usize,
    /// Token embedding.
    pub embed: PlainEmbed,
    /// Frame (time) embedding `[max_frames][d]`.
    pub time: Vec<f32>,
    /// Ego module.
    pub ego: Option<PlainEgo>,
    /// TAR blocks: (temporal, spatial).
    pub tar: Vec<(PlainSelf, PlainSelf)>,
    /// TAR's final norm.
    pub ln_tar: PlainNorm,
    /// The OAR's start vector `[d]`.
    pub bos: Vec<f32>,
    /// OAR layers.
    pub oar: Vec<PlainSelf>,
    /// OAR's final norm.
    pub ln_oar: PlainNorm,
    /// The tracked slots' projections into the TAR's input and output (`backbone.track`).
    pub track: Option<(PlainLinear, PlainLinear)>,
    /// TAR heads per segment (no bias).
    pub tar_heads: Vec<PlainLinear>,
    /// OAR heads per segment (no bias).
    pub oar_heads: Vec<PlainLinear>,
}

impl<B: Backend> FrameEmbedding<B> {
    pub(crate) fn plain(&self) -> PlainEmbed {
        let (tables, pos, fc1, fc2) = self.parts();
        let [_, e] = pos.val().dims();
        PlainEmbed {
            tables: tables
                .iter()
                .map(|(table, proj)| PlainTable {
                    rows: param(&table.weight),
                    dim: table.weight.val().dims()[1],
                    proj: proj.map(PlainLinear::of),
                })
                .collect(),
            pos: param(pos),
            e,
            fc1: PlainLinear::of(fc1),
            fc2: PlainLinear::of(fc2),
        }
    }
}

impl<B: Backend> EgoModule<B> {
    pub(crate) fn plain(&self) -> PlainEgo {
        let (queries, hist, env, ln, head, block, last) = self.parts();
        PlainEgo {
            queries: param(queries),
            q: queries.val().dims()[0],
            hist: hist.iter().map(PlainCross::of).collect(),
            env: env.iter().map(PlainCross::of).collect(),
            ln: PlainNorm::of(ln),
            head: PlainLinear::of(head),
            block,
            last,
        }
    }
}

impl<B: Backend> Heads<B> {
    pub(crate) fn plain(&self) -> Vec<PlainLinear> {
        self.linears().iter().map(PlainLinear::of).collect()
    }
}

impl<B: Backend> Backbone<B> {
    /// Every weight as plain f32 arrays (read back from the device once).
    pub fn plain(&self) -> PlainBackbone {
        let (time, tar, ln_tar, bos, oar, ln_oar, track) = self.parts();
        let d = self.embed_width();
        PlainBackbone {
            spec: self.spec().clone(),
            d,
            heads: oar.first().map_or(1, |b| b.parts().heads),
            embed: self.embed.plain(),
            time: param(time),
            ego: self.ego.as_ref().map(EgoModule::plain),
            tar: tar
                .iter()
                .map(|(t, s)| (PlainSelf::of(t), PlainSelf::of(s)))
                .collect(),
            ln_tar: PlainNorm::of(ln_tar),
            bos: param(bos),
            oar: oar.iter().map(PlainSelf::of).collect(),
            ln_oar: PlainNorm::of(ln_oar),
            track: track.map(|(i, o)| (PlainLinear::of(i), PlainLinear::of(o))),
            tar_heads: self.tar_heads.plain(),
            oar_heads: self.oar_heads.plain(),
        }
    }
}
