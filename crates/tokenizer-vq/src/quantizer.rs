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

/// Splits values in [-1, 1] into `hi + lo`: `hi` a multiple of 2⁻¹¹ (at most 11 significant bits, exact in
/// TF32's 10+1-bit significand), `lo` the rest (|lo| ≤ 2⁻¹², whose TF32 rounding errs by at most 2⁻²³). Dot
/// products of unit vectors as hi·hi + hi·lo + lo·hi then err by about 2⁻²² per term instead of 2⁻¹¹.
pub fn split_for_tf32<B: Backend>(x: Tensor<B, 2>) -> (Tensor<B, 2>, Tensor<B, 2>) {
    let hi = x.clone().mul_scalar(2048.0).round().div_scalar(2048.0);
    let lo = x - hi.clone();
    (hi, lo)
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
    ///
    /// The similarities are summed from high and low parts ([`split_for_tf32`]) so that they keep f32
    /// accuracy where the matrix product rounds its operands to TF32 (burn's tensor-core path on CUDA):
    /// neighbouring codes can be closer than TF32's rounding, and the ids would then depend on the device.
    pub fn nearest(&self, z: Tensor<B, 2>) -> Tensor<B, 1, Int> {
        let (c_hi, c_lo) = split_for_tf32(self.codes());
        let (c_hi, c_lo) = (c_hi.transpose(), c_lo.transpose());
        let n = z.dims()[0];
        let parts: Vec<_> = (0..n)
            .step_by(CHUNK)
            .map(|s| {
                let (z_hi, z_lo) = split_for_tf32(z.clone().detach().narrow(0, s, CHUNK.min(n - s)));
                let sim =
                    z_hi.clone().matmul(c_hi.clone()) + z_hi.matmul(c_lo.clone()) + z_lo.matmul(c_hi.clone());
                sim.argmax(1).squeeze_dim::<1>(1)
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use burn::tensor::TensorData;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    type F = burn::backend::Flex;

    /// An f32 rounded to TF32 (10 mantissa bits, to nearest, ties to even), as tensor cores read it.
    fn tf32(x: f32) -> f32 {
        let b = x.to_bits();
        f32::from_bits((b + 0x0fff + ((b >> 13) & 1)) & !0x1fff)
    }

    fn unit_rows(rng: &mut StdRng, n: usize, d: usize) -> Vec<Vec<f32>> {
        (0..n)
            .map(|_| {
                let v: Vec<f32> = (0..d).map(|_| rng.random_range(-1.0f32..1.0)).collect();
                let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                v.iter().map(|x| x / norm).collect()
            })
            .collect()
    }

    fn tensor(rows: &[Vec<f32>]) -> Tensor<F, 2> {
        let d = rows[0].len();
        Tensor::from_data(
            TensorData::new(rows.concat(), [rows.len(), d]),
            &Default::default(),
        )
    }

    fn host(t: Tensor<F, 2>) -> Vec<f32> {
        t.into_data().iter::<f32>().collect()
    }

    #[test]
    fn the_split_survives_tf32_and_restores_f32_dot_products() {
        let mut rng = StdRng::seed_from_u64(4);
        let (a, b) = (unit_rows(&mut rng, 64, 16), unit_rows(&mut rng, 64, 16));
        let (a_hi, a_lo) = split_for_tf32(tensor(&a));
        let (b_hi, b_lo) = split_for_tf32(tensor(&b));
        let (a_hi, a_lo, b_hi, b_lo) = (host(a_hi), host(a_lo), host(b_hi), host(b_lo));
        for (k, x) in a.concat().iter().enumerate() {
            assert_eq!(tf32(a_hi[k]), a_hi[k], "hi is exact in TF32");
            assert_eq!(a_hi[k] + a_lo[k], *x, "hi + lo is the value");
            assert!(a_lo[k].abs() <= 1.0 / 4096.0);
        }
        // Dot products with every operand rounded to TF32: plain, and summed from the parts.
        let (mut plain, mut split) = (0f64, 0f64);
        for i in 0..64 {
            for j in 0..64 {
                let exact: f64 = (0..16).map(|k| f64::from(a[i][k]) * f64::from(b[j][k])).sum();
                let dot = |x: &[f32], y: &[f32]| -> f64 {
                    (0..16)
                        .map(|k| f64::from(tf32(x[i * 16 + k])) * f64::from(tf32(y[j * 16 + k])))
                        .sum()
                };
                let (ah, al, bh, bl) = (&a_hi, &a_lo, &b_hi, &b_lo);
                plain = plain.max((dot(&a.concat(), &b.concat()) - exact).abs());
                split = split.max((dot(ah, bh) + dot(ah, bl) + dot(al, bh) - exact).abs());
            }
        }
        assert!(plain > 1e-4, "TF32 alone errs: {plain:e}");
        assert!(split < 2e-6, "the parts keep f32 accuracy: {split:e}");
    }

    #[test]
    fn nearest_tells_apart_codes_closer_than_tf32_rounding() {
        // Codes about 0.01 apart around a few centres, rows near them: their similarities differ by 1e-5 to 1e-4,
        // below TF32's rounding of the products (about 2e-4) but far above f32's.
        let mut rng = StdRng::seed_from_u64(8);
        let centres = unit_rows(&mut rng, 8, 16);
        let jitter = |v: &[f32], s: f32, rng: &mut StdRng| -> Vec<f32> {
            let w: Vec<f32> = v.iter().map(|x| x + rng.random_range(-s..s)).collect();
            let n = w.iter().map(|x| x * x).sum::<f32>().sqrt();
            w.iter().map(|x| x / n).collect()
        };
        let codes: Vec<Vec<f32>> = (0..256)
            .map(|i| jitter(&centres[i % 8], 0.005, &mut rng))
            .collect();
        let rows: Vec<Vec<f32>> = (0..512)
            .map(|i| jitter(&centres[i % 8], 0.005, &mut rng))
            .collect();
        let q = Quantizer::<F>::new(256, 16, &Default::default());
        let q = Quantizer {
            embed: Param::from_tensor(tensor(&codes)),
            ..q
        };
        let got: Vec<i64> = q.nearest(tensor(&rows)).into_data().iter::<i64>().collect();
        for (r, g) in rows.iter().zip(&got) {
            let sim =
                |c: &Vec<f32>| -> f64 { r.iter().zip(c).map(|(x, y)| f64::from(*x) * f64::from(*y)).sum() };
            let best = (0..256)
                .max_by(|&a, &b| sim(&codes[a]).total_cmp(&sim(&codes[b])))
                .unwrap();
            // Equal up to f32 ties.
            assert!(
                sim(&codes[best]) - sim(&codes[*g as usize]) < 1e-6,
                "{best} vs {g}"
            );
        }
    }
}
