use super::*;
use crate::kernels::{KeptInputs, Kernels};
use burn::backend::{Autodiff, Flex};
use burn::module::{Module, Param};
use burn::nn::LayerNormConfig;
use burn::tensor::Distribution;

type A = Autodiff<Flex>;

fn close<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>, tol: f32, what: &str) {
    let (a, b) = (a.flatten::<1>(0, D - 1), b.flatten::<1>(0, D - 1));
    let scale = b.clone().abs().max().into_scalar().max(1e-6);
    let err = (a - b).abs().max().into_scalar() / scale;
    assert!(err < tol, "{what}: relative error {err}");
}

fn norm(d: usize, shift: bool, dev: &burn::tensor::Device<A>) -> LayerNorm<A> {
    let mut ln = LayerNormConfig::new(d).with_bias(shift).init::<A>(dev);
    ln.gamma = Param::from_tensor(Tensor::random([d], Distribution::Normal(1.0, 0.3), dev));
    if shift {
        ln.beta = Some(Param::from_tensor(Tensor::random(
            [d],
            Distribution::Normal(0.0, 0.3),
            dev,
        )));
    }
    ln
}

#[test]
fn training_backends_take_the_operation() {
    assert!(tracked::<A>().is_some());
    assert!(tracked::<Autodiff<Flex, BalancedCheckpointing>>().is_some());
    assert!(tracked::<Flex>().is_none());
}

/// Values and the gradients of the input, scale and shift equal burn's `LayerNorm` (whose ε is therefore
/// [`LN_EPS`]), on 4 × 1026 rows of a 3-d input, with and without a shift; an input far from zero checks the
/// centred variance.
#[test]
fn layer_norm_matches_burns() {
    let dev = Default::default();
    for shift in [true, false] {
        let ln = norm(24, shift, &dev);
        let x = Tensor::<A, 3>::random([4, 1026, 24], Distribution::Normal(50.0, 2.0), &dev).require_grad();
        let w = Tensor::<A, 3>::random([4, 1026, 24], Distribution::Normal(0.0, 1.0), &dev);
        let ours = layer_norm(&ln, x.clone(), &Kernels::default());
        let theirs = ln.forward(x.clone());
        close(ours.clone().inner(), theirs.clone().inner(), 1e-5, "y");
        let g_ours = (ours * w.clone()).sum().backward();
        let g_theirs = (theirs * w).sum().backward();
        let x_grad = |g| x.grad(g).expect("x");
        close(x_grad(&g_ours), x_grad(&g_theirs), 1e-4, "dx");
        let gamma = ln.gamma.val();
        let grad = |t: &Tensor<A, 1>, g| t.grad(g).expect("grad");
        close(grad(&gamma, &g_ours), grad(&gamma, &g_theirs), 1e-4, "dgamma");
        if let Some(beta) = &ln.beta {
            let beta = beta.val();
            close(grad(&beta, &g_ours), grad(&beta, &g_theirs), 1e-4, "dbeta");
        }
    }
}

/// A frozen norm (no parameter gradients asked for) still passes the input's gradient.
#[test]
fn a_frozen_norm_passes_the_input_gradient() {
    let dev = Default::default();
    let ln = norm(8, true, &dev).no_grad();
    let x = Tensor::<A, 2>::random([5, 8], Distribution::Normal(0.0, 1.0), &dev).require_grad();
    let w = Tensor::<A, 2>::random([5, 8], Distribution::Normal(0.0, 1.0), &dev);
    let g_ours = (layer_norm(&ln, x.clone(), &Kernels::default()) * w.clone())
        .sum()
        .backward();
    let g_theirs = (ln.forward(x.clone()) * w).sum().backward();
    close(
        x.grad(&g_ours).expect("x"),
        x.grad(&g_theirs).expect("x"),
        1e-4,
        "dx",
    );
    assert!(ln.gamma.val().grad(&g_ours).is_none());
}

/// The two decomposed passes against a hand-computed row: x = [1, 2, 3, 6] has mean 3, variance 3.5.
#[test]
fn decomposed_passes_match_a_hand_computed_row() {
    let dev = Default::default();
    let x = Tensor::<Flex, 2>::from_floats([[1.0, 2.0, 3.0, 6.0]], &dev);
    let gamma = Tensor::<Flex, 1>::from_floats([1.0, 2.0, 1.0, 1.0], &dev);
    let beta = Tensor::<Flex, 1>::from_floats([0.0, 0.0, 0.5, 0.0], &dev);
    let normed = forward_decomposed(x.clone(), gamma.clone(), beta, 0.0, (FloatDType::F32, None));
    assert!(normed.kept.is_none());
    let (y, mean, rstd) = (normed.y, normed.mean, normed.rstd);
    let s = 1.0 / 3.5f32.sqrt();
    close(mean.clone(), Tensor::from_floats([3.0], &dev), 1e-6, "mean");
    close(rstd.clone(), Tensor::from_floats([s], &dev), 1e-6, "rstd");
    close(
        y,
        Tensor::from_floats([[-2.0 * s, -2.0 * s, 0.5, 3.0 * s]], &dev),
        1e-6,
        "y",
    );
    // dy = 1 on the first column only: dγ = x̂ there, dβ = 1 there, and dx = s·(g − mean g − x̂·mean(g·x̂))
    // with g = [1, 0, 0, 0].
    let dy = Tensor::<Flex, 2>::from_floats([[1.0, 0.0, 0.0, 0.0]], &dev);
    let (dx, dgamma, dbeta) = backward_decomposed(dy, x, mean, rstd, gamma);
    let xh = [-2.0 * s, -s, 0.0, 3.0 * s];
    let (mg, mgx) = (0.25, 0.25 * xh[0]);
    let want: Vec<f32> = (0..4)
        .map(|i| s * (f32::from(i == 0) - mg - xh[i] * mgx))
        .collect();
    close(
        dx,
        Tensor::<Flex, 1>::from_floats(want.as_slice(), &dev).reshape([1, 4]),
        1e-5,
        "dx",
    );
    close(
        dgamma,
        Tensor::from_floats([xh[0], 0.0, 0.0, 0.0], &dev),
        1e-6,
        "dgamma",
    );
    close(
        dbeta,
        Tensor::from_floats([1.0, 0.0, 0.0, 0.0], &dev),
        1e-6,
        "dbeta",
    );
}

/// A norm whose output feeds bf16 products keeps its input in bf16 (`kept_inputs = "operand"`): its
/// input gradient is the backward pass's on the bf16-rounded input with the forward pass's statistics
/// (from the unrounded input), and differs from keeping the input in f32.
#[test]
fn a_norm_feeding_bf16_products_keeps_its_input_in_bf16() {
    let dev = Default::default();
    let ln = norm(24, true, &dev);
    let x = Tensor::<Flex, 2>::random([64, 24], Distribution::Normal(0.0, 2.0), &dev);
    let dy = Tensor::<Flex, 2>::random([64, 24], Distribution::Normal(0.0, 1.0), &dev);
    let input_grad = |kept| {
        let x = Tensor::<A, 2>::from_inner(x.clone()).require_grad();
        let k = Kernels {
            kept_inputs: kept,
            ..Kernels::default()
        };
        let y = layer_norm_operand(&ln, x.clone(), crate::format::Precision::Bf16Linear, &k);
        let grads = (y.cast(FloatDType::F32) * Tensor::from_inner(dy.clone()))
            .sum()
            .backward();
        x.grad(&grads).expect("dx")
    };
    let gamma = ln.gamma.val().inner();
    let beta = ln.beta.as_ref().expect("a shift").val().inner();
    let normed = forward_decomposed(x.clone(), gamma.clone(), beta, LN_EPS, (FloatDType::F32, None));
    let (mean, rstd) = (normed.mean, normed.rstd);
    let bf16 = |t: Tensor<Flex, 2>| t.cast(FloatDType::BF16).cast(FloatDType::F32);
    // The output's gradient reaches the norm through its bf16 output: rounded to bf16 either way.
    let (rounded, dy) = (bf16(x.clone()), bf16(dy.clone()));
    let (expected, _, _) =
        backward_decomposed(dy.clone(), rounded, mean.clone(), rstd.clone(), gamma.clone());
    let kept_bf16 = input_grad(KeptInputs::Operand);
    assert_eq!(kept_bf16.clone().into_data(), expected.into_data());
    let kept_f32 = input_grad(KeptInputs::F32);
    let (exact, _, _) = backward_decomposed(dy, x, mean, rstd, gamma);
    assert_eq!(kept_f32.into_data(), exact.clone().into_data());
    let err = (kept_bf16 - exact.clone()).abs().max().into_scalar() / exact.abs().max().into_scalar();
    assert!(err > 0.0 && err < 2e-2, "bf16-kept input against f32: {err}");
}

/// The passes on a kept bf16 copy: the forward pass asked for one returns the input rounded to bf16 and
/// the same output as without; on the bf16 copy both passes give what they give on that copy widened to
/// f32 (the cast the kernels save), bit for bit.
#[test]
fn passes_keep_and_read_a_bf16_copy_as_its_widened_value() {
    let dev = Default::default();
    let x = Tensor::<Flex, 2>::random([32, 40], Distribution::Normal(1.0, 2.0), &dev);
    let dy = Tensor::<Flex, 2>::random([32, 40], Distribution::Normal(0.0, 1.0), &dev);
    let gamma = Tensor::<Flex, 1>::random([40], Distribution::Normal(1.0, 0.3), &dev);
    let beta = Tensor::<Flex, 1>::random([40], Distribution::Normal(0.0, 0.3), &dev);
    // The norm of `x` with output and kept-copy types `dtypes`, under the same γ and β.
    let norm =
        |x: Tensor<Flex, 2>, dtypes| forward_decomposed(x, gamma.clone(), beta.clone(), LN_EPS, dtypes);
    let plain = norm(x.clone(), (FloatDType::BF16, None));
    let keeping = norm(x.clone(), (FloatDType::BF16, Some(FloatDType::BF16)));
    let kept = keeping.kept.expect("a kept copy");
    assert_eq!(kept.dtype(), DType::BF16);
    assert_eq!(
        kept.clone().into_data(),
        x.clone().cast(FloatDType::BF16).into_data()
    );
    assert_eq!(keeping.y.into_data(), plain.y.into_data());

    let widened = kept.clone().cast(FloatDType::F32);
    let on_copy = norm(kept.clone(), (FloatDType::F32, None));
    let on_wide = norm(widened.clone(), (FloatDType::F32, None));
    assert_eq!(on_copy.y.into_data(), on_wide.y.into_data());
    let (mean, rstd) = (on_wide.mean, on_wide.rstd);
    let from_copy = backward_decomposed(dy.clone(), kept, mean.clone(), rstd.clone(), gamma.clone());
    let from_wide = backward_decomposed(dy, widened, mean, rstd, gamma);
    assert_eq!(from_copy.0.into_data(), from_wide.0.into_data());
    assert_eq!(from_copy.1.into_data(), from_wide.1.into_data());
    // And the copy is not the input: the rounding the comparisons above go through is there.
    let rounding = (x.clone().cast(FloatDType::BF16).cast(FloatDType::F32) - x)
        .abs()
        .max();
    assert!(rounding.into_scalar() > 0.0);
}
