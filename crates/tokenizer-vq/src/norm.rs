//! Group normalisation whose statistics are summed in two stages.
//!
//! burn's `GroupNorm` sums each (sample, group) in one reduction over `C/G · H · W` values. At the
//! `small` map tokenizer's full resolution that is 512 rows of 131,072 values per normalisation, too few
//! rows to occupy a GPU: on an H200 the reductions took 30% of a training step (docs/decisions/008-tokenizer-convolutions-and-kernel-compilation.md).
//! Summing each image row first (`b · G · C/G · H` rows of `W` values) and then the per-group partial sums
//! gives the same statistics from reductions that fill the device, and is no less accurate in f32. The
//! parameters are those of burn's [`GroupNorm`], so checkpoints and trained tokenizers are unchanged.

use burn::nn::GroupNorm;
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// `norm.forward(x)` for `x: [b, c, h, w]`, with two-stage sums.
pub fn group_norm<B: Backend>(norm: &GroupNorm<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [b, c, h, w] = x.dims();
    let g = norm.num_groups;
    let cg = c / g;
    let n = (cg * h * w) as f64;
    let x = x.reshape([b * g, cg * h, w]);
    let mean = group_sum(x.clone()).div_scalar(n);
    let centered = x - mean;
    let var = group_sum(centered.clone().square()).div_scalar(n);
    let y = (centered / var.add_scalar(norm.epsilon).sqrt()).reshape([b, c, h, w]);
    match (&norm.gamma, &norm.beta) {
        (Some(gamma), Some(beta)) => y * gamma.val().reshape([1, c, 1, 1]) + beta.val().reshape([1, c, 1, 1]),
        _ => y,
    }
}

/// Per-group sums `[b·G, 1, 1]` of `[b·G, C/G·H, W]`: rows of `W`, then the row sums.
fn group_sum<B: Backend>(x: Tensor<B, 3>) -> Tensor<B, 3> {
    x.sum_dim(2).sum_dim(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::module::Param;
    use burn::nn::GroupNormConfig;
    use burn::tensor::Distribution;

    type A = Autodiff<Flex>;

    /// A norm with non-trivial affine parameters (burn starts them at 1 and 0).
    fn norm(groups: usize, c: usize) -> GroupNorm<A> {
        let dev = Default::default();
        let mut n = GroupNormConfig::new(groups, c).with_epsilon(1e-6).init::<A>(&dev);
        n.gamma = Some(Param::from_tensor(Tensor::random(
            [c],
            Distribution::Uniform(0.5, 1.5),
            &dev,
        )));
        n.beta = Some(Param::from_tensor(Tensor::random(
            [c],
            Distribution::Uniform(-0.5, 0.5),
            &dev,
        )));
        n
    }

    /// max |a − b| / max |b|: differences on the scale of the tensor, so that values near zero do not
    /// turn rounding into large relative errors.
    fn scaled_difference(a: Vec<f32>, b: Vec<f32>) -> f32 {
        let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(f32::MIN_POSITIVE);
        a.iter().zip(&b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
    }

    /// Output and input/gamma/beta gradients against burn's `GroupNorm`, on inputs with a large mean
    /// (where a one-pass variance would lose digits) and uneven per-channel scales.
    #[test]
    fn matches_burns_group_norm_and_its_gradients() {
        let dev = Default::default();
        A::seed(&dev, 11);
        for (groups, shape) in [
            (2, [2, 6, 5, 7]),
            (4, [3, 8, 4, 4]),
            (1, [1, 3, 9, 2]),
            (3, [2, 3, 1, 1]),
        ] {
            let n = norm(groups, shape[1]);
            let x0 = Tensor::<A, 4>::random(shape, Distribution::Normal(3.0, 2.0), &dev)
                * Tensor::<A, 4>::random([1, shape[1], 1, 1], Distribution::Uniform(0.1, 4.0), &dev);
            let dy = Tensor::<A, 4>::random(shape, Distribution::Normal(0.0, 1.0), &dev);
            let run = |ours: bool| {
                let x = Tensor::<A, 4>::from_data(x0.to_data(), &dev).require_grad();
                let y = if ours {
                    group_norm(&n, x.clone())
                } else {
                    n.forward(x.clone())
                };
                let grads = (y.clone() * dy.clone()).sum().backward();
                let gx = x.grad(&grads).expect("input gradient");
                let gg = n
                    .gamma
                    .as_ref()
                    .and_then(|p| p.val().grad(&grads))
                    .expect("gamma gradient");
                let gb = n
                    .beta
                    .as_ref()
                    .and_then(|p| p.val().grad(&grads))
                    .expect("beta gradient");
                (y.inner(), gx, gg, gb)
            };
            let (ours, theirs) = (run(true), run(false));
            let pairs = [(ours.0, theirs.0), (ours.1, theirs.1)];
            let params = [(ours.2, theirs.2), (ours.3, theirs.3)];
            for (what, (a, b)) in ["output", "input gradient"].iter().zip(pairs) {
                let err = scaled_difference(
                    a.into_data().to_vec().expect("f32"),
                    b.into_data().to_vec().expect("f32"),
                );
                assert!(err < 1e-5, "{what} of {shape:?}/{groups}: {err:e}");
            }
            for (what, (a, b)) in ["gamma gradient", "beta gradient"].iter().zip(params) {
                let err = scaled_difference(
                    a.into_data().to_vec().expect("f32"),
                    b.into_data().to_vec().expect("f32"),
                );
                assert!(err < 1e-5, "{what} of {shape:?}/{groups}: {err:e}");
            }
        }
    }

    /// Groups are runs of adjacent channels: moving one channel's values to another group changes only
    /// the statistics of the groups involved, and a constant group normalises to β.
    #[test]
    fn groups_are_adjacent_channels() {
        let dev = Default::default();
        let n = GroupNormConfig::new(2, 4).with_epsilon(1e-6).init::<Flex>(&dev);
        let mut v = vec![5.0f32; 4 * 3];
        v[6..].copy_from_slice(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let y = group_norm(
            &n,
            Tensor::<Flex, 1>::from_floats(v.as_slice(), &dev).reshape([1, 4, 3, 1]),
        );
        let y: Vec<f32> = y.into_data().to_vec().expect("f32");
        assert!(y[..6].iter().all(|v| v.abs() < 1e-3), "constant group: {y:?}");
        let mean = y[6..].iter().sum::<f32>() / 6.0;
        let var = y[6..].iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / 6.0;
        assert!(mean.abs() < 1e-5 && (var - 1.0).abs() < 1e-3, "{y:?}");
    }
}
