//! Starting rows for ordered value bins (`backbone.ordinal_init`).
//!
//! The ego action and the agents' values are scalars cut into bins; a table drawn at random gives bin 500
//! and bin 501 unrelated embeddings, so the model must learn every bin's neighbourhood from data before a
//! position at bin 500 tells it anything about the next frame's bin 503. Starting the rows as a sinusoid of
//! the bin index (the authors' ego embedding is such a table, kept fixed) makes nearby bins alike from the
//! first step, and a shift by k bins a rotation of each sin/cos pair: a linear map.

use burn::module::Param;
use burn::nn::{Embedding, Linear};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

/// Row-major `[rows, width]` table: row `b` holds `sin(b·ω_i)` at even column `2i` and `cos(b·ω_i)` at
/// odd column `2i + 1`, with frequencies `ω_i` spaced geometrically from 1 down to `1 / rows` radians per
/// bin, so that every pair of rows differs and neighbouring rows are alike over the whole range.
pub fn sinusoid(rows: usize, width: usize) -> Vec<f32> {
    let pairs = width.div_ceil(2).max(1);
    let low = 1.0 / (rows.max(2) as f64);
    let omega: Vec<f64> = (0..pairs)
        .map(|i| low.powf(i as f64 / (pairs.max(2) - 1) as f64))
        .collect();
    let mut out = Vec::with_capacity(rows * width);
    for b in 0..rows {
        for j in 0..width {
            let phase = b as f64 * omega[j / 2];
            out.push(if j % 2 == 0 { phase.sin() } else { phase.cos() } as f32);
        }
    }
    out
}

/// `table` with its first `ordinal` rows replaced by [`sinusoid`] rows scaled to unit variance per value,
/// the scale of burn's default embedding initialisation.
pub fn embedding<B: Backend>(mut table: Embedding<B>, ordinal: usize) -> Embedding<B> {
    if let Some(w) = leading(table.weight.val(), 0, ordinal, std::f64::consts::SQRT_2) {
        table.weight = Param::from_tensor(w);
    }
    table
}

/// A bias-free `head` (weight `[d, vocab]`) with the columns of its first `ordinal` ids replaced by
/// [`sinusoid`] rows scaled to the spread of burn's default initialisation (uniform in ±1/√d), so that
/// nearby bins start with correlated logits and the first loss stays near ln(vocab).
pub fn head<B: Backend>(mut head: Linear<B>, ordinal: usize) -> Linear<B> {
    let d = head.weight.dims()[0];
    if let Some(w) = leading(head.weight.val(), 1, ordinal, (2.0 / (3.0 * d as f64)).sqrt()) {
        head.weight = Param::from_tensor(w);
    }
    head
}

/// `w` with its first `ordinal` slices along `dim` (rows for 0, columns for 1) replaced by `scale` ×
/// [`sinusoid`] (one table row per slice); `None` when there is nothing to replace. Detached: on an
/// autodiff backend a parameter must be a leaf, not the result of `cat`.
fn leading<B: Backend>(w: Tensor<B, 2>, dim: usize, ordinal: usize, scale: f64) -> Option<Tensor<B, 2>> {
    let dims = w.dims();
    let (len, width) = (dims[dim], dims[1 - dim]);
    let ordinal = ordinal.min(len);
    if ordinal == 0 {
        return None;
    }
    let table = TensorData::new(sinusoid(ordinal, width), [ordinal, width]);
    let mut block = Tensor::<B, 2>::from_data(table, &w.device()).mul_scalar(scale);
    if dim == 1 {
        block = block.transpose();
    }
    Some(if ordinal == len {
        block.detach()
    } else {
        Tensor::cat(vec![block, w.narrow(dim, ordinal, len - ordinal)], dim).detach()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::Flex;
    use burn::nn::{EmbeddingConfig, LinearConfig};

    type B = Flex;

    fn row(t: &[f32], w: usize, b: usize) -> &[f32] {
        &t[b * w..(b + 1) * w]
    }

    fn cosine(a: &[f32], b: &[f32]) -> f64 {
        let dot: f64 = a.iter().zip(b).map(|(x, y)| f64::from(*x) * f64::from(*y)).sum();
        let n = |v: &[f32]| v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
        dot / (n(a) * n(b))
    }

    #[test]
    fn values_and_neighbourhoods() {
        let (rows, w) = (1024, 64);
        let t = sinusoid(rows, w);
        assert_eq!(t.len(), rows * w);
        // Row 3: sin and cos of 3·ω with ω_0 = 1 and the last pair's ω = 1/1024.
        assert!((t[3 * w] - 3f32.sin()).abs() < 1e-6 && (t[3 * w + 1] - 3f32.cos()).abs() < 1e-6);
        assert!((t[3 * w + w - 2] - (3.0f32 / 1024.0).sin()).abs() < 1e-6);
        // Similarity falls with the distance between bins, and no two bins coincide.
        let near = cosine(row(&t, w, 500), row(&t, w, 501));
        let mid = cosine(row(&t, w, 500), row(&t, w, 540));
        let far = cosine(row(&t, w, 500), row(&t, w, 900));
        assert!(near > 0.9 && near > mid && mid > far, "{near} {mid} {far}");
        for b in 0..rows - 1 {
            assert!(
                cosine(row(&t, w, b), row(&t, w, b + 1)) < 0.999,
                "bins {b} and {}",
                b + 1
            );
        }
    }

    #[test]
    fn only_the_ordinal_rows_change_at_the_default_scale() {
        let dev = Default::default();
        let table = EmbeddingConfig::new(12, 8).init::<B>(&dev);
        let before = table.weight.val().into_data().to_vec::<f32>().unwrap();
        let after = embedding(table, 10)
            .weight
            .val()
            .into_data()
            .to_vec::<f32>()
            .unwrap();
        let expect = sinusoid(10, 8);
        for (i, v) in after.iter().enumerate() {
            let want = if i < 80 {
                expect[i] * std::f32::consts::SQRT_2
            } else {
                before[i]
            };
            assert!((v - want).abs() < 1e-6, "value {i}: {v} vs {want}");
        }

        let lin = LinearConfig::new(6, 5).with_bias(false).init::<B>(&dev);
        let before = lin.weight.val().into_data().to_vec::<f32>().unwrap();
        let after = head(lin, 3).weight.val().into_data().to_vec::<f32>().unwrap();
        let expect = sinusoid(3, 6);
        let scale = (2.0f32 / 18.0).sqrt();
        for r in 0..6 {
            for c in 0..5 {
                let want = if c < 3 {
                    expect[c * 6 + r] * scale
                } else {
                    before[r * 5 + c]
                };
                assert!((after[r * 5 + c] - want).abs() < 1e-6, "[{r}, {c}]");
            }
        }
        // Every id ordinal (the ego action's vocabulary), and nothing to replace.
        let all = head(LinearConfig::new(4, 3).with_bias(false).init::<B>(&dev), 3);
        assert_eq!(all.weight.dims(), [4, 3]);
        assert_eq!(
            embedding(EmbeddingConfig::new(5, 4).init::<B>(&dev), 5)
                .weight
                .dims(),
            [5, 4]
        );
        // Nothing to replace: the layer comes back as it was.
        let table = EmbeddingConfig::new(4, 2).init::<B>(&dev);
        let before = table.weight.val().into_data();
        assert_eq!(embedding(table, 0).weight.val().into_data(), before);
    }
}
