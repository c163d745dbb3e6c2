//! Token embedding (paper eq. 2): `e = MLP(Embed_modality(z) + PE(position))`.

use crate::config::Precision;
use crate::spec::BackboneSpec;
use burn::module::{Module, Param};
use burn::nn::{Dropout, DropoutConfig, Embedding, EmbeddingConfig, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Int, Tensor, TensorData};
use umgen_ops::Kernels;
use umgen_ops::linear::linear;
use umgen_ops::mlp::gelu_mlp;

/// One segment's table: learnable rows (initialised from the modality's codebook when it has one, then
/// projected to the embedding width).
#[derive(Module, Debug)]
pub struct SegmentTable<B: Backend> {
    table: Embedding<B>,
    proj: Option<Linear<B>>,
}

/// Embeds every position of a frame.
#[derive(Module, Debug)]
pub struct FrameEmbedding<B: Backend> {
    tables: Vec<SegmentTable<B>>,
    pos: Param<Tensor<B, 2>>,
    fc1: Linear<B>,
    fc2: Linear<B>,
    drop: Dropout,
    blocks: Vec<[usize; 2]>,
    precision: Precision,
}

impl<B: Backend> FrameEmbedding<B> {
    /// Tables for every segment of `spec`, width `e`, output width `d`, products in `precision`; the first
    /// `ordinal[s]` rows of segment `s`'s table start as a sinusoid ([`crate::ordinal`]; none past the
    /// slice's end).
    pub fn new(
        spec: &BackboneSpec,
        e: usize,
        d: usize,
        dropout: f64,
        precision: Precision,
        ordinal: &[usize],
        dev: &B::Device,
    ) -> Self {
        let tables = spec
            .segments
            .iter()
            .enumerate()
            .map(|(i, s)| match &s.codebook {
                Some((dim, data)) => {
                    let mut table = EmbeddingConfig::new(s.embed_vocab, *dim).init(dev);
                    // Content rows from the codebook; start/end rows random at the codebook's scale.
                    let scale = (data.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>()
                        / data.len().max(1) as f64)
                        .sqrt();
                    let content =
                        Tensor::<B, 2>::from_data(TensorData::new(data.clone(), [s.vocab, *dim]), dev);
                    let rest = Tensor::<B, 2>::random(
                        [s.embed_vocab - s.vocab, *dim],
                        Distribution::Normal(0.0, scale.max(1e-3)),
                        dev,
                    );
                    table.weight = Param::from_tensor(Tensor::cat(vec![content, rest], 0));
                    SegmentTable {
                        table,
                        proj: Some(LinearConfig::new(*dim, e).init(dev)),
                    }
                }
                None => SegmentTable {
                    table: crate::ordinal::embedding(
                        EmbeddingConfig::new(s.embed_vocab, e).init(dev),
                        ordinal.get(i).copied().unwrap_or(0),
                    ),
                    proj: None,
                },
            })
            .collect();
        Self {
            tables,
            pos: Param::from_tensor(Tensor::random([spec.n, e], Distribution::Normal(0.0, 0.02), dev)),
            fc1: LinearConfig::new(e, d).init(dev),
            fc2: LinearConfig::new(d, d).init(dev),
            drop: DropoutConfig::new(dropout).init(),
            blocks: spec
                .segments
                .iter()
                .map(|s| [s.block_start, s.block_len])
                .collect(),
            precision,
        }
    }

    /// Embeddings `[m, d]` of tokens `ids` `[m]` all at frame position `p` (for decoding one token at a
    /// time; equal to row `p` of [`forward`](Self::forward)).
    pub fn forward_at(&self, p: usize, ids: Tensor<B, 1, Int>) -> Tensor<B, 2> {
        let m = ids.dims()[0];
        let s = self.segment_of(p, 1).unwrap_or(0);
        let y = self.rows(s, p, ids.reshape([m, 1]), &Kernels::DEFAULT);
        let d = y.dims()[2];
        y.reshape([m, d])
    }

    /// Embeddings `[m, l, d]` of tokens `ids` `[m, l]` at frame positions `p..p + l`, which must lie in one
    /// segment's block (for decoding several positions at once; equal to those rows of
    /// [`forward`](Self::forward)). `None` when they do not.
    pub fn forward_block(&self, p: usize, ids: Tensor<B, 2, Int>) -> Option<Tensor<B, 3>> {
        self.block_with(p, ids, &Kernels::DEFAULT)
    }

    /// [`Self::forward_block`] with the kernels `k` (the training pass's tracked slots).
    pub(crate) fn block_with(&self, p: usize, ids: Tensor<B, 2, Int>, k: &Kernels) -> Option<Tensor<B, 3>> {
        let s = self.segment_of(p, ids.dims()[1])?;
        Some(self.rows(s, p, ids, k))
    }

    /// Each segment's table and projection, the position embeddings and the MLP's two layers.
    #[allow(clippy::type_complexity)]
    pub(crate) fn parts(
        &self,
    ) -> (
        Vec<(&Embedding<B>, Option<&Linear<B>>)>,
        &Param<Tensor<B, 2>>,
        &Linear<B>,
        &Linear<B>,
    ) {
        let tables = self.tables.iter().map(|t| (&t.table, t.proj.as_ref())).collect();
        (tables, &self.pos, &self.fc1, &self.fc2)
    }

    /// The number format of its products (the backbone's).
    pub(crate) fn precision(&self) -> Precision {
        self.precision
    }

    /// The segment whose block holds positions `p..p + l` (`l` ≥ 1).
    fn segment_of(&self, p: usize, l: usize) -> Option<usize> {
        self.blocks
            .iter()
            .position(|[start, len]| l > 0 && p >= *start && p + l <= start + len)
    }

    /// Embeddings `[m, l, d]` of `ids` `[m, l]` at positions `p..p + l` of segment `s`'s block.
    fn rows(&self, s: usize, p: usize, ids: Tensor<B, 2, Int>, k: &Kernels) -> Tensor<B, 3> {
        let l = ids.dims()[1];
        let t = &self.tables[s];
        let x = umgen_ops::lookup::embed(&t.table, ids);
        let x = match &t.proj {
            Some(proj) => linear(proj, x, self.precision, k),
            None => x,
        };
        let e = x.dims()[2];
        self.mlp(x + self.pos.val().narrow(0, p, l).reshape([1, l, e]), k)
    }

    /// Embeddings `[b, f, N, d]` of frames of tokens `[b, f, N]`, with the kernels `k`.
    pub fn forward(&self, tokens: Tensor<B, 3, Int>, k: &Kernels) -> Tensor<B, 4> {
        let [b, f, n] = tokens.dims();
        let flat = tokens.reshape([b * f, n]);
        let parts: Vec<Tensor<B, 3>> = self
            .tables
            .iter()
            .zip(&self.blocks)
            .map(|(t, [start, len])| {
                let x = umgen_ops::lookup::embed(&t.table, flat.clone().narrow(1, *start, *len));
                match &t.proj {
                    Some(p) => linear(p, x, self.precision, k),
                    None => x,
                }
            })
            .collect();
        let x = Tensor::cat(parts, 1) + self.pos.val().unsqueeze_dim::<3>(0);
        let x = self.mlp(x, k);
        let d = x.dims()[2];
        x.reshape([b, f, n, d])
    }

    /// The embedding MLP (paper eq. 2) with dropout.
    fn mlp<const D: usize>(&self, x: Tensor<B, D>, k: &Kernels) -> Tensor<B, D> {
        let p = self.precision;
        self.drop.forward(gelu_mlp(&self.fc1, &self.fc2, x, p, k))
    }
}
