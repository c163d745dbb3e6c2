//! The vector quantiser: unit-norm codes matched by cosine similarity, updated by exponential moving
//! averages of the encoder outputs assigned to them (BEiT-v2's NormEMA, as the official release uses),
//! with dead codes restarted from current encoder outputs. Gradients pass straight through.

use burn::module::{Module, Param};
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, IndexingUpdateOp, Int, Tensor};

/// Rows are compared against the codebook in chunks of this many, bounding the similarity matrix.
const CHUNK: usize = 4096;

/// Unit rows.
pub fn normalize<B: Backend>(x: Tensor<B, 2>) -> Tensor<B, 2> {
    let n = x.clone().powf_scalar(2.0).sum_dim(1).sqrt().clamp_min(1e-6);
    x / n
}

/// The codebook and its moving averages (saved with the model, never touched by the optimiser).
#[derive(Module, Debug)]
pub struct Quantizer<B: Backend> {
    /// Unit-norm code vectors `[K, D]`.
    pub embed: Param<Tensor<B, 2>>,
    embed_sum: Param<Tensor<B, 2>>,
    cluster_size: Param<Tensor<B, 1>>,
}

/// What quantising a batch gives.
#[derive(Debug, Clone)]
pub struct Quantized<B: Backend> {
    /// Unit-norm encoder outputs `[N, D]` (carrying gradients).
    pub z: Tensor<B, 2>,
    /// Their codes, with straight-through gradients to `z` `[N, D]`.
    pub z_q: Tensor<B, 2>,
    /// Code index per row `[N]`.
    pub indices: Tensor<B, 1, Int>,
}

impl<B: Backend> Quantizer<B> {
    /// `k` random unit codes of size `d`.
    pub fn new(k: usize, d: usize, dev: &B::Device) -> Self {
        let embed = normalize(Tensor::random([k, d], Distribution::Normal(0.0, 1.0), dev));
        Self {
            embed: Param::from_tensor(embed.clone()),
            embed_sum: Param::from_tensor(embed),
            cluster_size: Param::from_tensor(Tensor::ones([k], dev)),
        }
    }

    /// Codebook entries.
    pub fn size(&self) -> usize {
        self.embed.dims()[0]
    }

    /// The codebook, outside any gradient graph.
    pub fn codes(&self) -> Tensor<B, 2> {
        self.embed.val().detach()
    }

    /// Nearest code (largest cosine similarity) of unit rows `z` `[N, D]`.
    pub fn nearest(&self, z: Tensor<B, 2>) -> Tensor<B, 1, Int> {
        let codes_t = self.codes().transpose();
        let n = z.dims()[0];
        let parts: Vec<_> = (0..n)
            .step_by(CHUNK)
            .map(|s| {
                z.clone()
                    .detach()
                    .narrow(0, s, CHUNK.min(n - s))
                    .matmul(codes_t.clone())
                    .argmax(1)
                    .squeeze_dim::<1>(1)
            })
            .collect();
        Tensor::cat(parts, 0)
    }

    /// Code vectors of indices `[N]` → `[N, D]`.
    pub fn lookup(&self, indices: Tensor<B, 1, Int>) -> Tensor<B, 2> {
        self.codes().select(0, indices)
    }

    /// Quantises encoder outputs `[N, D]` (normalised here).
    pub fn quantize(&self, z: Tensor<B, 2>) -> Quantized<B> {
        let z = normalize(z);
        let indices = self.nearest(z.clone());
        let codes = self.lookup(indices.clone());
        let z_q = z.clone() + (codes - z.clone()).detach();
        Quantized { z, z_q, indices }
    }

    /// What a batch contributes to the moving averages, flat so that ranks can sum it in one collective:
    /// `[K]` assignment counts, then the `[K, D]` sums of the (detached, unit) vectors assigned to each code.
    pub fn assignment(&self, z: Tensor<B, 2>, indices: Tensor<B, 1, Int>) -> Tensor<B, 1> {
        let [n, d] = z.dims();
        let k = self.size();
        let dev = z.device();
        let counts = Tensor::<B, 1>::zeros([k], &dev).select_assign(
            0,
            indices.clone(),
            Tensor::ones([n], &dev),
            IndexingUpdateOp::Add,
        );
        let sums =
            Tensor::<B, 2>::zeros([k, d], &dev).select_assign(0, indices, z.detach(), IndexingUpdateOp::Add);
        Tensor::cat(vec![counts, sums.reshape([k * d])], 0)
    }

    /// One moving-average step towards the mean of the vectors assigned to each code, from
    /// [`Quantizer::assignment`]'s statistics (of one batch, or summed over the ranks' batches).
    pub fn ema_apply(self, stats: Tensor<B, 1>, decay: f64) -> Self {
        let [k, d] = self.embed.dims();
        let counts = stats.clone().narrow(0, 0, k);
        let sums = stats.narrow(0, k, k * d).reshape([k, d]);
        let cluster = self.cluster_size.val().detach().mul_scalar(decay) + counts.mul_scalar(1.0 - decay);
        let embed_sum = self.embed_sum.val().detach().mul_scalar(decay) + sums.mul_scalar(1.0 - decay);
        self.replace(normalize(embed_sum.clone()), embed_sum, cluster)
    }

    /// Sets codes `which` to `vectors` (unit rows, one per code).
    pub fn restart(self, which: Tensor<B, 1, Int>, vectors: Tensor<B, 2>) -> Self {
        let vectors = normalize(vectors.detach());
        let set2 = |t: Tensor<B, 2>| {
            let old = t.clone().select(0, which.clone());
            t.select_assign(0, which.clone(), vectors.clone() - old, IndexingUpdateOp::Add)
        };
        let embed = set2(self.embed.val().detach());
        let embed_sum = set2(self.embed_sum.val().detach());
        let cs = self.cluster_size.val().detach();
        let old = cs.clone().select(0, which.clone());
        let cluster = cs.select_assign(0, which.clone(), old.neg().add_scalar(1.0), IndexingUpdateOp::Add);
        self.replace(embed, embed_sum, cluster)
    }

    fn replace(self, embed: Tensor<B, 2>, embed_sum: Tensor<B, 2>, cluster: Tensor<B, 1>) -> Self {
        Self {
            embed: Param::initialized(self.embed.id, embed),
            embed_sum: Param::initialized(self.embed_sum.id, embed_sum),
            cluster_size: Param::initialized(self.cluster_size.id, cluster),
        }
    }
}
