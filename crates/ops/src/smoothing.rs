//! Ordinal label smoothing (`train.ordinal_sigma`): the cross-entropy of ordered value bins against a
//! discretised Gaussian around the target bin instead of the bin alone.
//!
//! With 1024 bins of 0.125 m, a hard target scores the agent's true bin and gives bin 501 the same loss
//! as bin 900 when the truth is 500: the gradient says nothing about being close. A target spread over the
//! neighbouring bins rewards near misses, which is what the L2 measures in `umgen eval`. The loss reported
//! for a smoothed target is KL(q ‖ p) = Σ q log q − Σ q log p, not Σ q log p, so that it is 0 for a perfect
//! prediction and equals the plain negative log-likelihood when σ is 0 (the entropy of q carries no
//! gradient: it only keeps the logged numbers comparable across σ).

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};

/// Summed loss of log-probabilities `lp` `[rows, vocab]` against `targets` `[rows, 1]`: the negative
/// log-likelihood where `sigma` is 0 or there are no ordinal ids; otherwise, for targets below `ordinal`
/// (the ordered bins), KL(q ‖ p) with q ∝ exp(−(j − t)² / 2σ²) over the bins `j` within ⌈3σ⌉ of the target
/// `t` and inside `0..ordinal`; other targets (categories, pads) stay hard.
pub fn nll_sum<B: Backend>(
    lp: Tensor<B, 2>,
    targets: Tensor<B, 2, Int>,
    ordinal: usize,
    sigma: f64,
) -> Tensor<B, 1> {
    let vocab = lp.dims()[1];
    let q = Targets::new(targets, ordinal, sigma, vocab);
    q.entropy() - (lp.gather(1, q.ids.clone()) * q.weights).sum()
}

/// The target distribution q of each row: ids `[rows, k]` (inside `0..vocab`) and their weights `[rows,
/// k]`, which sum to 1 per row (`k` = 1 and weight 1 for hard targets).
#[derive(Debug, Clone)]
pub struct Targets<B: Backend> {
    /// Ids with weight (ids of zero weight are clamped into the vocabulary).
    pub ids: Tensor<B, 2, Int>,
    /// Weights, summing to 1 per row.
    pub weights: Tensor<B, 2>,
}

impl<B: Backend> Targets<B> {
    /// q for `targets` `[rows, 1]` as [`nll_sum`] defines it.
    pub fn new(targets: Tensor<B, 2, Int>, ordinal: usize, sigma: f64, vocab: usize) -> Self {
        let dev = targets.device();
        let rows = targets.dims()[0];
        if sigma <= 0.0 || ordinal == 0 {
            return Self {
                ids: targets,
                weights: Tensor::ones([rows, 1], &dev),
            };
        }
        let (offsets, gauss) = window(sigma);
        let k = offsets.len();
        let offs = Tensor::<B, 2, Int>::from_data(TensorData::new(offsets.clone(), [1, k]), &dev);
        let gauss = Tensor::<B, 2>::from_data(TensorData::new(gauss, [1, k]), &dev);
        let centre: Vec<f32> = offsets.iter().map(|&o| if o == 0 { 1.0 } else { 0.0 }).collect();
        let centre = Tensor::<B, 2>::from_data(TensorData::new(centre, [1, k]), &dev);

        let idx = targets.clone().expand([rows, k]) + offs.expand([rows, k]);
        let inside =
            idx.clone().greater_equal_elem(0).float() * idx.clone().lower_elem(ordinal as i64).float();
        let ordered = targets.lower_elem(ordinal as i64).float();
        let w = gauss * inside * ordered.clone() + centre * ordered.neg().add_scalar(1.0);
        Self {
            ids: idx.clamp(0, vocab as i64 - 1),
            weights: w.clone() / w.sum_dim(1),
        }
    }

    /// Σ q log q over all rows (0 for hard targets): what turns −Σ q log p into KL(q ‖ p).
    pub fn entropy(&self) -> Tensor<B, 1> {
        let w = self.weights.clone();
        // Hard targets (one id of weight 1 per row) have none; no pass over their rows for it.
        if w.dims()[1] == 1 {
            return Tensor::zeros([1], &w.device());
        }
        // 0 · log(0 + ε) is 0, so bins outside the window add nothing.
        (w.clone() * w.add_scalar(1e-30).log()).sum()
    }
}

/// Offsets `−r..=r` (r = ⌈3σ⌉) and their unnormalised Gaussian weights.
fn window(sigma: f64) -> (Vec<i64>, Vec<f32>) {
    let r = (3.0 * sigma).ceil() as i64;
    let offsets: Vec<i64> = (-r..=r).collect();
    let gauss = offsets
        .iter()
        .map(|&o| (-(o * o) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    (offsets, gauss)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::Flex;
    use burn::tensor::activation::log_softmax;

    type B = Flex;

    fn lp(rows: &[Vec<f32>]) -> Tensor<B, 2> {
        let v = rows[0].len();
        let flat: Vec<f32> = rows.concat();
        log_softmax(
            Tensor::from_data(TensorData::new(flat, [rows.len(), v]), &Default::default()),
            1,
        )
    }

    fn ids(t: &[i64]) -> Tensor<B, 2, Int> {
        Tensor::from_data(TensorData::new(t.to_vec(), [t.len(), 1]), &Default::default())
    }

    fn value(x: Tensor<B, 1>) -> f64 {
        x.into_scalar() as f64
    }

    /// KL against an independent computation on the host, with the window cut at both ends of the bins,
    /// and a category target (id ≥ ordinal) kept hard.
    #[test]
    fn matches_a_host_computation() {
        let logits = vec![
            vec![0.3, -1.0, 2.0, 0.5, 0.0, 1.5, -0.2, 0.7],
            vec![1.0, 0.2, -0.5, 0.1, 0.9, -1.3, 0.4, 0.0],
            vec![-0.4, 0.8, 0.3, 1.1, -0.6, 0.2, 2.2, -1.0],
        ];
        let (ordinal, sigma) = (6usize, 0.8);
        let targets = [1i64, 5, 7];
        let got = value(nll_sum(lp(&logits), ids(&targets), ordinal, sigma));

        let mut want = 0.0;
        for (row, &t) in logits.iter().zip(&targets) {
            let z: f64 = row.iter().map(|&x| (x as f64).exp()).sum::<f64>().ln();
            let logp = |j: usize| row[j] as f64 - z;
            if t as usize >= ordinal {
                want -= logp(t as usize);
                continue;
            }
            let q: Vec<(usize, f64)> = (0..ordinal)
                .filter(|&j| (j as i64 - t).abs() <= 3)
                .map(|j| {
                    (
                        j,
                        (-((j as f64 - t as f64).powi(2)) / (2.0 * sigma * sigma)).exp(),
                    )
                })
                .collect();
            let s: f64 = q.iter().map(|(_, w)| w).sum();
            for (j, w) in q {
                let w = w / s;
                want += w * (w.ln() - logp(j));
            }
        }
        assert!((got - want).abs() < 1e-4, "{got} vs {want}");
    }

    #[test]
    fn sigma_zero_is_the_plain_nll() {
        let logits = vec![vec![0.3, -1.0, 2.0, 0.5], vec![1.0, 0.2, -0.5, 0.1]];
        let plain = value(lp(&logits).gather(1, ids(&[2, 0])).sum().neg());
        let got = value(nll_sum(lp(&logits), ids(&[2, 0]), 4, 0.0));
        assert!((got - plain).abs() < 1e-6);
    }

    /// A prediction equal to q scores 0; moving mass one bin away scores more than keeping it near.
    #[test]
    fn rewards_near_misses() {
        let (ordinal, sigma, t) = (16usize, 1.0, 8usize);
        let (offsets, gauss) = window(sigma);
        let mut q = vec![1e-9f32; ordinal];
        for (o, g) in offsets.iter().zip(&gauss) {
            q[(t as i64 + o) as usize] = *g;
        }
        let logq: Vec<f32> = q.iter().map(|x| x.ln()).collect();
        let exact = value(nll_sum(lp(&[logq]), ids(&[t as i64]), ordinal, sigma));
        assert!(exact.abs() < 1e-3, "{exact}");

        let peaked = |at: usize| {
            let row: Vec<f32> = (0..ordinal).map(|j| if j == at { 5.0 } else { 0.0 }).collect();
            value(nll_sum(lp(&[row]), ids(&[t as i64]), ordinal, sigma))
        };
        assert!(peaked(t) < peaked(t + 1));
        assert!(peaked(t + 1) < peaked(t + 4));
    }
}
