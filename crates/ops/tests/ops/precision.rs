//! Mixed precision: bf16 products with f32 master weights, linear layers and attention apart.

use burn::backend::{Autodiff, Flex};
use burn::nn::LinearConfig;
use burn::tensor::{DType, Distribution, Tensor};
use umgen_ops::attention::attend;
use umgen_ops::linear::linear;
use umgen_ops::{Kernels, Precision};

type A = Autodiff<Flex>;

fn rel(a: Tensor<Flex, 3>, b: Tensor<Flex, 3>) -> f32 {
    let scale = b.clone().abs().max().into_scalar();
    (a - b).abs().max().into_scalar() / scale
}

#[test]
fn bf16_linear_is_close_to_f32_and_keeps_f32_gradients() {
    let dev = Default::default();
    let layer = LinearConfig::new(48, 24).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([2, 5, 48], Distribution::Normal(0.0, 1.0), &dev).require_grad();
    let full = linear(&layer, x.clone(), Precision::F32, &Kernels::DEFAULT);
    let half = linear(&layer, x.clone(), Precision::Bf16, &Kernels::DEFAULT);
    assert_eq!(half.dtype(), DType::F32);
    let err = rel(half.clone().inner(), full.clone().inner());
    // bf16 keeps 8 significant bits: products of 48 terms land near 2⁻⁸ relative, never at zero.
    assert!(err > 1e-5 && err < 2e-2, "relative error {err}");
    let g_half = half.sum().backward();
    let g_full = full.sum().backward();
    let w = layer.weight.val();
    let (gw_half, gw_full) = (w.grad(&g_half).expect("grad"), w.grad(&g_full).expect("grad"));
    assert_eq!(gw_half.dtype(), DType::F32);
    let err = rel(gw_half.unsqueeze(), gw_full.unsqueeze());
    assert!(err < 2e-2, "weight gradient relative error {err}");
    let bias = layer.bias.as_ref().expect("bias").val();
    assert_eq!(bias.grad(&g_half).expect("bias grad").dtype(), DType::F32);
    assert_eq!(x.grad(&g_half).expect("input grad").dtype(), DType::F32);
}

#[test]
fn bf16_linear_casts_linear_layers_and_leaves_attention_in_f32() {
    let dev = Default::default();
    let layer = LinearConfig::new(48, 24).init::<A>(&dev);
    let x = Tensor::<A, 3>::random([2, 5, 48], Distribution::Normal(0.0, 1.0), &dev);
    let half = linear(&layer, x.clone(), Precision::Bf16, &Kernels::DEFAULT).inner();
    let mixed = linear(&layer, x, Precision::Bf16Linear, &Kernels::DEFAULT).inner();
    assert_eq!(
        rel(mixed, half),
        0.0,
        "linear layers: the same bf16 products as `bf16`"
    );
    // 300 keys take the training attention's tiled operation on the CPU, whose products follow the
    // precision it is given.
    let qkv = |seed: f64| Tensor::<A, 4>::random([1, 2, 300, 16], Distribution::Normal(seed, 1.0), &dev);
    let (q, k, v) = (qkv(0.0), qkv(0.1), qkv(-0.1));
    let att = |p| {
        attend(q.clone(), k.clone(), v.clone(), None, true, p, &Kernels::DEFAULT)
            .inner()
            .flatten::<3>(0, 1)
    };
    let (full, bf16, mixed) = (
        att(Precision::F32),
        att(Precision::Bf16),
        att(Precision::Bf16Linear),
    );
    assert_eq!(rel(mixed, full.clone()), 0.0, "attention: f32 products");
    assert!(
        rel(bf16, full) > 1e-5,
        "bf16 attention products differ from f32 ones"
    );
    assert_eq!(Precision::Bf16Linear.attention(), Precision::F32);
    let parsed: Precision = serde_json::from_str(r#""bf16-linear""#).expect("bf16-linear parses");
    assert_eq!(parsed, Precision::Bf16Linear);
}
