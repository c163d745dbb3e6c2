use super::*;
use crate::kernels::Kernels;
use crate::mlp::gelu_mlp;
use burn::backend::Flex;
use burn::nn::LinearConfig;
use burn::tensor::Distribution;

/// The default kernels (the fused bias + GELU).
const K: Kernels = Kernels::DEFAULT;

type A = Autodiff<Flex>;

fn values<const D: usize>(t: Tensor<Flex, D>) -> Vec<f64> {
    let data = t.cast(FloatDType::F32).into_data();
    data.to_vec::<f32>()
        .expect("f32 values")
        .into_iter()
        .map(f64::from)
        .collect()
}

/// The largest |a − b| over the largest |b|.
fn rel(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(1e-12_f64, |m, v| m.max(v.abs()));
    a.iter().zip(b).fold(0.0_f64, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// Φ(x) in f64 by Simpson's rule on the normal density from 0 to x (4,000 intervals: exact to about
/// 1e-14 for the |x| < 10 here), independent of any erf implementation.
fn normal_cdf(x: f64) -> f64 {
    let pdf = |t: f64| (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
    let steps = 4000;
    let h = x / steps as f64;
    let inner: f64 = (1..steps)
        .map(|i| if i % 2 == 1 { 4.0 } else { 2.0 } * pdf(i as f64 * h))
        .sum();
    0.5 + h / 3.0 * (pdf(0.0) + inner + pdf(x))
}

fn gelu_ref(x: f64) -> (f64, f64) {
    let cdf = normal_cdf(x);
    let pdf = (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    (x * cdf, cdf + x * pdf)
}

/// Everything the reference computes for `gelu(x · w + b)` over `rows` rows of `k`, `n` outputs, and a
/// loss Σ h · r: the activation and the gradients of x, w and b.
struct Reference {
    h: Vec<f64>,
    dx: Vec<f64>,
    dw: Vec<f64>,
    db: Vec<f64>,
}

fn reference(x: &[f64], w: &[f64], b: &[f64], r: &[f64], (rows, k, n): (usize, usize, usize)) -> Reference {
    let mut h = vec![0.0; rows * n];
    let mut dpre = vec![0.0; rows * n];
    for i in 0..rows {
        for j in 0..n {
            let pre = b[j] + (0..k).map(|t| x[i * k + t] * w[t * n + j]).sum::<f64>();
            let (g, dg) = gelu_ref(pre);
            h[i * n + j] = g;
            dpre[i * n + j] = r[i * n + j] * dg;
        }
    }
    let dx = (0..rows * k)
        .map(|at| (0..n).map(|j| dpre[at / k * n + j] * w[at % k * n + j]).sum())
        .collect();
    let dw = (0..k * n)
        .map(|at| (0..rows).map(|i| x[i * k + at / n] * dpre[i * n + at % n]).sum())
        .collect();
    let db = (0..n).map(|j| (0..rows).map(|i| dpre[i * n + j]).sum()).collect();
    Reference { h, dx, dw, db }
}

#[test]
fn training_backends_take_the_operation() {
    assert!(tracked::<A>(&K).is_some());
    assert!(tracked::<Autodiff<Flex, BalancedCheckpointing>>(&K).is_some());
    assert!(tracked::<Flex>(&K).is_none());
}

/// The activation and the gradients of the input, weight and bias equal GELU's exact form and derivative
/// computed in f64 (pre-activations spread over ±6, so both tails count); with bf16 products the
/// activation comes out in bf16, within bf16's rounding of the reference.
#[test]
fn linear_gelu_matches_an_f64_reference() {
    let dev = Default::default();
    let (b, l, k, n) = (3, 7, 5, 12);
    let layer = LinearConfig::new(k, n).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([b, l, k], Distribution::Normal(0.0, 2.0), &dev).require_grad();
    let r = Tensor::<A, 3>::random([b, l, n], Distribution::Normal(0.0, 1.0), &dev);
    let bias = layer.bias.as_ref().expect("a bias").val();
    let expected = reference(
        &values(x.clone().inner()),
        &values(layer.weight.val().inner()),
        &values(bias.clone().inner()),
        &values(r.clone().inner()),
        (b * l, k, n),
    );
    // bf16 rounds the products' operands and the results by up to 2⁻⁸ each.
    for (p, out, tol) in [
        (Precision::F32, FloatDType::F32, 1e-5),
        (Precision::Bf16, FloatDType::BF16, 0.03),
    ] {
        let h = linear_gelu(&layer, x.clone(), p, &K);
        assert_eq!(h.dtype(), out.into(), "{p:?}");
        let grads = (h.clone().cast(FloatDType::F32) * r.clone()).sum().backward();
        let h = values(h.inner());
        assert!(rel(&h, &expected.h) < tol, "{p:?} h: {}", rel(&h, &expected.h));
        let grad = |t: Tensor<A, 3>| values(t.grad(&grads).expect("gradient"));
        let dx = grad(x.clone());
        let dw = values(layer.weight.val().grad(&grads).expect("weight gradient"));
        let db = values(bias.grad(&grads).expect("bias gradient"));
        for (what, got, want) in [
            ("dx", &dx, &expected.dx),
            ("dw", &dw, &expected.dw),
            ("db", &db, &expected.db),
        ] {
            assert!(rel(got, want) < tol, "{p:?} {what}: {}", rel(got, want));
        }
    }
}

/// From a bf16 product the activation and the pre-activation's gradient come out in bf16, and they are
/// the f32 computation on the same values rounded: the bias add and GELU run in f32, nothing but the final
/// rounding differs. The bias's gradient stays f32.
#[test]
fn bf16_passes_are_the_f32_ones_rounded() {
    let dev = Default::default();
    let y = Tensor::<Flex, 2>::random([9, 16], Distribution::Normal(0.0, 3.0), &dev).cast(FloatDType::BF16);
    let dh = Tensor::<Flex, 2>::random([9, 16], Distribution::Normal(0.0, 1.0), &dev).cast(FloatDType::BF16);
    let b = Tensor::<Flex, 1>::random([16], Distribution::Normal(0.0, 1.0), &dev);
    let wide = |t: &Tensor<Flex, 2>| t.clone().cast(FloatDType::F32);
    let f32s = forward_decomposed(wide(&y), b.clone());
    let bf16s = forward_decomposed(y.clone(), b.clone());
    assert_eq!(bf16s.dtype(), FloatDType::BF16.into());
    assert_eq!(values(f32s.cast(FloatDType::BF16)), values(bf16s));
    let (d32, db32) = backward_decomposed(wide(&dh), wide(&y), b.clone());
    let (d16, db16) = backward_decomposed(dh, y, b);
    assert_eq!(d16.dtype(), FloatDType::BF16.into());
    assert_eq!(db16.dtype(), FloatDType::F32.into());
    assert_eq!(values(d32.cast(FloatDType::BF16)), values(d16));
    assert_eq!(values(db32), values(db16));
}

/// The MLP with bf16 products: its output and every gradient are f32 and within bf16's rounding of the f32
/// MLP's, though its hidden activation, pre-activation and their gradients are bf16.
#[test]
fn a_bf16_mlp_keeps_f32_results_close_to_the_f32_one() {
    let dev = Default::default();
    let fc = LinearConfig::new(8, 32).init::<A>(&dev);
    let out = LinearConfig::new(32, 8).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([2, 5, 8], Distribution::Normal(0.0, 1.0), &dev).require_grad();
    let r = Tensor::<A, 3>::random([2, 5, 8], Distribution::Normal(0.0, 1.0), &dev);
    let run = |p| {
        let y = gelu_mlp(&fc, &out, x.clone(), p, &K);
        assert_eq!(y.dtype(), FloatDType::F32.into(), "{p:?}");
        let g = (y.clone() * r.clone()).sum().backward();
        let grads = [
            x.grad(&g).expect("dx"),
            fc.weight.val().grad(&g).expect("fc dw").unsqueeze(),
            out.weight.val().grad(&g).expect("out dw").unsqueeze(),
        ];
        for t in &grads {
            assert_eq!(t.dtype(), FloatDType::F32.into(), "{p:?}");
        }
        let fc_db = fc.bias.as_ref().expect("bias").val().grad(&g).expect("fc db");
        (y.inner(), grads, fc_db)
    };
    let (y32, g32, db32) = run(Precision::F32);
    let (y16, g16, db16) = run(Precision::Bf16);
    let close = |a: Tensor<Flex, 3>, b: Tensor<Flex, 3>, what: &str| {
        let e = rel(&values(a), &values(b));
        assert!(e > 1e-6 && e < 0.03, "{what}: {e}");
    };
    close(y16, y32, "y");
    for ((a, b), what) in g16.into_iter().zip(g32).zip(["dx", "fc dw", "out dw"]) {
        close(a, b, what);
    }
    close(db16.unsqueeze(), db32.unsqueeze(), "fc db");
}

/// The operation's forward pass is burn's `gelu(linear)` (same erf), and the bias gradient of the
/// decomposed backward pass is the column sum of the pre-activation's gradient.
#[test]
fn forward_matches_burns_and_the_bias_gradient_sums_the_columns() {
    let dev = Default::default();
    let layer = LinearConfig::new(6, 10).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([2, 300, 6], Distribution::Normal(0.0, 1.5), &dev);
    let ours = linear_gelu(&layer, x.clone(), Precision::F32, &K).inner();
    let burns = gelu(linear(&layer, x, Precision::F32, &K)).inner();
    assert!(rel(&values(ours), &values(burns)) < 1e-6);
    let y = Tensor::<Flex, 2>::random([600, 10], Distribution::Normal(0.0, 1.5), &dev);
    let dh = Tensor::<Flex, 2>::random([600, 10], Distribution::Normal(0.0, 1.0), &dev);
    let bias = Tensor::<Flex, 1>::random([10], Distribution::Normal(0.0, 1.0), &dev);
    let (d, db) = backward_decomposed(dh, y, bias);
    assert!(rel(&values(db), &values(d.sum_dim(0).reshape([10]))) < 1e-5);
}

/// With `recompute_gelu` the second product's backward pass recomputes the activation (counted) and gives
/// the same output and gradients, bit for bit, as keeping it, in f32 and bf16; without it nothing is
/// recomputed.
#[test]
fn a_recomputed_activation_gives_the_kept_ones_gradients_exactly() {
    let dev = Default::default();
    let fc = LinearConfig::new(8, 32).init::<A>(&dev);
    let out = LinearConfig::new(32, 8).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([2, 5, 8], Distribution::Normal(0.0, 1.0), &dev).require_grad();
    let r = Tensor::<A, 3>::random([2, 5, 8], Distribution::Normal(0.0, 1.0), &dev);
    let run = |p, recompute_gelu| {
        let k = Kernels { recompute_gelu, ..K };
        let before = crate::mlp::recomputed();
        let y = gelu_mlp(&fc, &out, x.clone(), p, &k);
        let g = (y.clone() * r.clone()).sum().backward();
        let bias = |l: &Linear<A>| l.bias.as_ref().expect("bias").val().grad(&g).expect("db");
        let values = [
            values(y.inner()),
            values(x.grad(&g).expect("dx")),
            values(fc.weight.val().grad(&g).expect("fc dw")),
            values(out.weight.val().grad(&g).expect("out dw")),
            values(bias(&fc)),
            values(bias(&out)),
        ];
        (values, crate::mlp::recomputed() - before)
    };
    for p in [Precision::F32, Precision::Bf16] {
        let (kept, none) = run(p, false);
        let (recomputed, once) = run(p, true);
        assert_eq!(none, 0, "{p:?}: recomputed with recompute_gelu off");
        assert!(once >= 1, "{p:?}: the recomputing path was not taken");
        assert_eq!(recomputed, kept, "{p:?}");
    }
}
