#![allow(clippy::unwrap_used, clippy::expect_used)]

use super::*;
use crate::format::Precision;
use crate::kernels::{KeptInputs, Kernels, LayerKernel};
use burn::backend::Flex;
use burn::module::Param;
use burn::module::{Module, ModuleMapper, ModuleVisitor};
use burn::nn::{LayerNormConfig, LinearConfig};
use burn::tensor::module::attention;
use burn::tensor::ops::{AttentionModuleOptions, FloatTensorOps};
use burn::tensor::{FloatDType, TensorMetadata, TensorPrimitive};

type A = Autodiff<Flex>;

/// A pre-norm self-attention layer's parameters, in the order the backbone's layer visits them.
#[derive(Module, Debug)]
struct TestLayer<B: Backend> {
    ln1: LayerNorm<B>,
    q: Linear<B>,
    kv: Linear<B>,
    proj: Linear<B>,
    ln2: LayerNorm<B>,
    fc: Linear<B>,
    out: Linear<B>,
    heads: usize,
}

impl<B: Backend> TestLayer<B> {
    fn parts(&self) -> LayerParts<'_, B> {
        LayerParts {
            ln1: &self.ln1,
            ln_ctx: None,
            q: &self.q,
            kv: &self.kv,
            proj: &self.proj,
            ln2: &self.ln2,
            fc: &self.fc,
            out: &self.out,
            heads: self.heads,
            precision: Precision::F32,
            attn_dropout: 0.0,
            mlp_dropout: 0.0,
        }
    }
}

/// A layer of width `d` (MLP 2d) whose parameters are all perturbed, so that a gradient formula that drops
/// a scale or shift (norms start at γ = 1, β = 0) cannot pass.
fn layer(d: usize, heads: usize) -> TestLayer<A> {
    struct Noise;
    impl ModuleMapper<A> for Noise {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<A, D>>) -> Param<Tensor<A, D>> {
            param.map(|t| {
                let noisy = t.clone().inner() + t.inner().random_like(Distribution::Normal(0.0, 0.2));
                Tensor::from_inner(noisy).require_grad()
            })
        }
    }
    Flex::seed(&Default::default(), 11);
    let dev = Default::default();
    let lin = |i, o| LinearConfig::new(i, o).init(&dev);
    TestLayer {
        ln1: LayerNormConfig::new(d).init(&dev),
        q: lin(d, d),
        kv: lin(d, 2 * d),
        proj: lin(d, d),
        ln2: LayerNormConfig::new(d).init(&dev),
        fc: lin(d, 2 * d),
        out: lin(2 * d, d),
        heads,
    }
    .map(&mut Noise)
}

/// Every parameter gradient of `blk` in `grads`, in visiting order.
fn param_grads(blk: &TestLayer<A>, grads: &Gradients) -> Vec<Tensor<Flex, 1>> {
    struct Collect<'a>(&'a Gradients, Vec<Tensor<Flex, 1>>);
    impl ModuleVisitor<A> for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
            let g = param.val().grad(self.0).expect("every parameter has a gradient");
            self.1.push(g.flatten(0, D - 1));
        }
    }
    let mut c = Collect(grads, Vec::new());
    blk.visit(&mut c);
    c.1
}

/// Largest difference relative to the largest magnitude of `b`.
fn rel<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>) -> f32 {
    let scale = b.clone().abs().max().into_scalar().max(1e-12);
    (a - b).abs().max().into_scalar() / scale
}

/// Output and gradients (input, then parameters) of `(f(x) · r).sum()`.
fn run(
    blk: &TestLayer<A>,
    x: &Tensor<Flex, 3>,
    r: &Tensor<Flex, 3>,
    f: impl Fn(&TestLayer<A>, Tensor<A, 3>) -> Tensor<A, 3>,
) -> (Tensor<Flex, 3>, Tensor<Flex, 3>, Vec<Tensor<Flex, 1>>) {
    let x = Tensor::<A, 3>::from_inner(x.clone()).require_grad();
    let y = f(blk, x.clone());
    let grads = (y.clone() * Tensor::from_inner(r.clone())).sum().backward();
    (y.inner(), x.grad(&grads).unwrap(), param_grads(blk, &grads))
}

/// A layer of width 16 with 2 heads, an input `[2, 24, 16]` and the output's weights, drawn in that order
/// after the layer's seed.
fn case() -> (TestLayer<A>, Tensor<Flex, 3>, Tensor<Flex, 3>) {
    let dev = Default::default();
    let blk = layer(16, 2);
    let x = Tensor::<Flex, 3>::random([2, 24, 16], Distribution::Normal(0.0, 1.0), &dev);
    let r = Tensor::<Flex, 3>::random([2, 24, 16], Distribution::Normal(0.0, 1.0), &dev);
    (blk, x, r)
}

/// Dropout keep-masks (keeping 0.7) of the attention's and the MLP's outputs shaped like `x`, drawn from
/// `seeds`.
fn masks(x: &Tensor<Flex, 3>, seeds: [u64; 2]) -> Masks<Flex> {
    let mask = |seed| {
        Flex::seed(&x.device(), seed);
        let m = x.random_like(Distribution::Bernoulli(0.7)).greater_elem(0.5);
        Some((m, 1.0 / 0.7))
    };
    Masks {
        attn: mask(seeds[0]),
        mlp: mask(seeds[1]),
    }
}

/// The written-out passes' setting for [`case`]'s layer in f32.
fn setting(causal: bool) -> Setting {
    Setting {
        heads: 2,
        causal,
        precision: Precision::F32,
        eps: crate::norm::LN_EPS,
        over_time: None,
        kernels: Kernels::default(),
    }
}

/// A parameter's gradient from the written-out passes, flattened.
fn flat(g: TensorPrimitive<Flex>) -> Tensor<Flex, 1> {
    let g = g.tensor();
    let n = g.shape().num_elements();
    Tensor::from_primitive(TensorPrimitive::Float(Flex::float_reshape(g, [n].into())))
}

/// The operation, recomputing and keeping, against burn's autodiff of the layer written out with burn's
/// attention, without dropout: outputs and all 14 gradients.
#[test]
fn the_layer_op_matches_burns_operations() {
    let (blk, x, r) = case();
    let reference = |b: &TestLayer<A>, x: Tensor<A, 3>| {
        let p = b.parts();
        let n = p.ln1.forward(x.clone());
        let split = |t| crate::heads::split_heads(t, p.heads);
        let kv = p.kv.forward(n.clone());
        let (k, v) = (split(kv.clone().narrow(2, 0, 16)), split(kv.narrow(2, 16, 16)));
        let opts = AttentionModuleOptions {
            is_causal: true,
            ..Default::default()
        };
        let att = attention(split(p.q.forward(n)), k, v, None, None, opts);
        let x1 = x + p.proj.forward(crate::heads::merge_heads(att));
        let h = burn::tensor::activation::gelu(p.fc.forward(p.ln2.forward(x1.clone())));
        x1 + p.out.forward(h)
    };
    let (y0, dx0, dp0) = run(&blk, &x, &r, reference);
    for recompute in [true, false] {
        let k = Kernels {
            recompute,
            layer: LayerKernel::Fused,
            ..Kernels::default()
        };
        let (y1, dx1, dp1) = run(&blk, &x, &r, |b, x| {
            self_layer::<Flex, NoCheckpointing>(&b.parts(), x, true, None, &k).expect("a layer with biases")
        });
        assert!(rel(y1, y0.clone()) < 1e-4, "recompute {recompute}: output");
        assert!(
            rel(dx1, dx0.clone()) < 1e-4,
            "recompute {recompute}: input gradient"
        );
        assert_eq!(dp1.len(), 14);
        for (i, (a, b)) in dp1.into_iter().zip(dp0.clone()).enumerate() {
            let e = rel(a, b);
            assert!(
                e < 1e-4,
                "recompute {recompute}: parameter {i}: relative error {e}"
            );
        }
    }
}

#[test]
fn dropout_masks_of_the_forward_pass_are_reused_by_the_backward_pass() {
    // The written-out passes with given masks against burn's autodiff of the same layer with the same
    // masks applied by hand.
    let (blk, x, r) = case();
    let masks = masks(&x, [1, 2]);
    let (attn_mask, mlp_mask) = (masks.attn.clone().unwrap().0, masks.mlp.clone().unwrap().0);
    let reference = |b: &TestLayer<A>, x: Tensor<A, 3>| {
        let p = b.parts();
        let keep = |t: Tensor<A, 3>, m: &Tensor<Flex, 3, burn::tensor::Bool>| {
            t * Tensor::from_inner(m.clone().float() / 0.7)
        };
        let n = p.ln1.forward(x.clone());
        let split = |t| crate::heads::split_heads(t, p.heads);
        let kv = p.kv.forward(n.clone());
        let (k, v) = (split(kv.clone().narrow(2, 0, 16)), split(kv.narrow(2, 16, 16)));
        let att = attention(
            split(p.q.forward(n)),
            k,
            v,
            None,
            None,
            AttentionModuleOptions::default(),
        );
        let x1 = x + keep(p.proj.forward(crate::heads::merge_heads(att)), &attn_mask);
        let h = burn::tensor::activation::gelu(p.fc.forward(p.ln2.forward(x1.clone())));
        x1 + keep(p.out.forward(h), &mlp_mask)
    };
    let (y0, dx0, dp0) = run(&blk, &x, &r, reference);

    let parts = blk.parts();
    let (weights, _) = weights(&parts).unwrap();
    let setting = setting(false);
    let (y1, _) = math::forward(&weights, setting, &masks, x.clone(), None, Keep::NOTHING);
    let (dx1, dctx, dp1) = math::backward(&weights, setting, &masks, (x, None), r);
    assert!(dctx.is_none(), "a self-attention layer has no context");
    assert!(rel(y1, y0) < 1e-4);
    assert!(rel(dx1, dx0) < 1e-4);
    // Weights' order is the parameters' visiting order (ln1, attn q/kv/proj, ln2, mlp fc/proj).
    for (i, (a, b)) in dp1.into_iter().zip(dp0).enumerate() {
        let e = rel(flat(a), b);
        assert!(e < 1e-4, "parameter {i}: relative error {e}");
    }
}

#[test]
fn the_operation_is_handed_out_for_training_backends_only_and_when_asked_for() {
    assert!(on::<A, Flex>().is_some());
    assert!(on::<Flex, Flex>().is_none());
    let on = Kernels {
        recompute: true,
        ..Kernels::DEFAULT
    };
    assert!(layer_op_for::<A>(&on).is_some());
    assert!(layer_op_for::<A>(&Kernels::DEFAULT).is_none(), "off by default");
    assert!(layer_op_for::<Flex>(&on).is_none());
    let fused = Kernels {
        layer: LayerKernel::Fused,
        ..Kernels::DEFAULT
    };
    assert!(layer_op_for::<A>(&fused).is_some());
    assert!(cross_op_for::<A>(&fused).is_some());
    assert!(cross_op_for::<Flex>(&fused).is_none());
}

#[test]
fn a_layer_without_biases_is_handed_back() {
    let mut blk = layer(8, 2);
    blk.q.bias = None;
    let x = Tensor::<A, 3>::random([1, 4, 8], Distribution::Normal(0.0, 1.0), &Default::default());
    let back = self_layer::<Flex, NoCheckpointing>(&blk.parts(), x.clone(), false, None, &Kernels::DEFAULT)
        .expect_err("the operation takes layers with biases only");
    assert_eq!(back.into_data(), x.into_data());
}

/// Under bf16 products the layer keeps its input in bf16 (`kept_inputs = "operand"`): its gradients
/// are exactly those of a layer that kept the bf16-rounded input in f32, and differ from keeping the input
/// itself; the forward pass reads the input unrounded either way.
#[test]
fn a_layer_under_bf16_products_keeps_its_input_rounded_to_bf16() {
    let dev = Default::default();
    let blk = layer(16, 2);
    let x = Tensor::<Flex, 3>::random([2, 24, 16], Distribution::Normal(0.0, 1.0), &dev);
    let rounded = x.clone().cast(FloatDType::BF16).cast(FloatDType::F32);
    assert!(
        rel(rounded.clone(), x.clone()) > 0.0,
        "the input has bits bf16 drops"
    );
    let r = Tensor::<Flex, 3>::random([2, 24, 16], Distribution::Normal(0.0, 1.0), &dev);
    let keeping = |input| {
        move |b: &TestLayer<A>, x: Tensor<A, 3>| {
            let parts = LayerParts {
                precision: Precision::Bf16Linear,
                ..b.parts()
            };
            let kernels = Kernels {
                kept_inputs: input,
                recompute: true,
                ..Kernels::default()
            };
            self_layer::<Flex, NoCheckpointing>(&parts, x, true, None, &kernels).expect("a layer with biases")
        }
    };
    let (y, dx, dp) = run(&blk, &x, &r, keeping(KeptInputs::Operand));
    let (_, dx_rounded, dp_rounded) = run(&blk, &rounded, &r, keeping(KeptInputs::F32));
    let (y_f32, dx_f32, _) = run(&blk, &x, &r, keeping(KeptInputs::F32));
    assert_eq!(
        y.into_data(),
        y_f32.into_data(),
        "the forward pass reads the input as it is"
    );
    assert_eq!(dx.clone().into_data(), dx_rounded.into_data());
    for (i, (a, b)) in dp.into_iter().zip(dp_rounded).enumerate() {
        assert_eq!(a.into_data(), b.into_data(), "parameter {i}");
    }
    let e = rel(dx, dx_f32);
    assert!(
        e > 0.0 && e < 2e-2,
        "input gradient against the f32-kept input: {e}"
    );
}

/// The layer keeping its activations (`layer = "fused"`) against the same layer recomputing them, with
/// its inputs kept in f32 (so the recomputation reads exactly what the forward pass did): the same output
/// and the same gradients bit for bit, in f32 and under bf16 products, whether it keeps the MLP's
/// activation or recomputes it (`recompute_gelu`). Under `kept_inputs = "operand"` the kept layer reads
/// the forward pass's own second norm input, which the recomputation cannot: the gradients differ.
#[test]
fn a_kept_layer_gives_the_recomputed_layers_gradients() {
    let (blk, x, r) = case();
    let with = |precision, kernels: Kernels| {
        move |b: &TestLayer<A>, x: Tensor<A, 3>| {
            let parts = LayerParts {
                precision,
                ..b.parts()
            };
            self_layer::<Flex, NoCheckpointing>(&parts, x, true, None, &kernels).expect("a layer with biases")
        }
    };
    let f32_kept = Kernels {
        kept_inputs: KeptInputs::F32,
        ..Kernels::DEFAULT
    };
    let recomputing = Kernels {
        recompute: true,
        ..f32_kept
    };
    for precision in [Precision::F32, Precision::Bf16Linear] {
        let (y0, dx0, dp0) = run(&blk, &x, &r, with(precision, recomputing));
        for recompute_gelu in [true, false] {
            let keeping = Kernels {
                layer: LayerKernel::Fused,
                recompute_gelu,
                ..f32_kept
            };
            let before = layers_kept();
            let (y1, dx1, dp1) = run(&blk, &x, &r, with(precision, keeping));
            assert!(layers_kept() > before, "the kept path ran");
            let what = format!("{precision:?}, recompute_gelu {recompute_gelu}");
            assert_eq!(y1.into_data(), y0.clone().into_data(), "{what}: output");
            assert_eq!(dx1.into_data(), dx0.clone().into_data(), "{what}: input gradient");
            for (i, (a, b)) in dp1.into_iter().zip(dp0.clone()).enumerate() {
                assert_eq!(a.into_data(), b.into_data(), "{what}: parameter {i}");
            }
        }
    }
    let operand = |kernels: Kernels| with(Precision::Bf16Linear, kernels);
    let (_, dx_rec, _) = run(
        &blk,
        &x,
        &r,
        operand(Kernels {
            recompute: true,
            ..Kernels::DEFAULT
        }),
    );
    let (_, dx_kept, _) = run(
        &blk,
        &x,
        &r,
        operand(Kernels {
            layer: LayerKernel::Fused,
            ..Kernels::DEFAULT
        }),
    );
    let e = rel(dx_kept, dx_rec);
    assert!(e > 0.0 && e < 2e-2, "bf16-kept inputs: {e}");
}

/// With dropout the kept layer's backward pass applies its forward pass's masks: its gradients are those
/// of the written-out passes recomputing from the same masks.
#[test]
fn a_kept_layer_reuses_its_dropout_masks() {
    let (blk, x, r) = case();
    let masks = masks(&x, [3, 4]);
    let parts = blk.parts();
    let (weights, _) = weights(&parts).unwrap();
    let setting = setting(true);
    let all = Keep {
        format: None,
        all: true,
    };
    let (y0, _) = math::forward(&weights, setting, &masks, x.clone(), None, Keep::NOTHING);
    let (y1, kept) = math::forward(&weights, setting, &masks, x.clone(), None, all);
    assert_eq!(y1.into_data(), y0.into_data());
    let math::Kept::Activations(f) = kept else {
        panic!("a layer keeping its activations keeps them");
    };
    let (dx0, _, dp0) = math::backward(&weights, setting, &masks, (x, None), r.clone());
    let (dx1, _, dp1) = math::gradients(&weights, setting, &masks, *f, r);
    assert_eq!(dx1.into_data(), dx0.into_data());
    for (i, (a, b)) in dp1.into_iter().zip(dp0).enumerate() {
        assert_eq!(flat(a).into_data(), flat(b).into_data(), "parameter {i}");
    }
}
