//! [`FusedAdamW`] against burn's `OptimizerAdaptor<AdamW>`: the same steps, the same records.

use super::*;
use crate::clip_grad_norm;
use crate::kernels::{
    AdamWSlot, AdamWStep, AdamWStepped, GradNorm, MultiTensor, adamw_reference, norm_reference,
};
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::{Int, Tolerance};

type B = burn::backend::Autodiff<burn::backend::Flex>;
type Inner = burn::backend::Flex;

#[derive(Module, Debug)]
struct Net<B: Backend> {
    a: Linear<B>,
    b: Linear<B>,
}

const SETTINGS: AdamWSettings = AdamWSettings {
    beta_1: 0.9,
    beta_2: 0.95,
    epsilon: 1e-8,
    weight_decay: 0.1,
};

/// A net whose weights are drawn (burn draws them lazily, so clones made before the first read would each
/// draw their own).
fn net() -> Net<B> {
    let dev = Default::default();
    let n = Net {
        a: LinearConfig::new(5, 4).init(&dev),
        b: LinearConfig::new(4, 3).init(&dev),
    };
    drop(weights(&n));
    n
}

fn burn_adamw() -> OptimizerAdaptor<AdamW, Net<B>, B> {
    AdamWConfig::new()
        .with_beta_1(SETTINGS.beta_1)
        .with_beta_2(SETTINGS.beta_2)
        .with_epsilon(SETTINGS.epsilon)
        .with_weight_decay(SETTINGS.weight_decay)
        .init()
}

/// The gradients of a loss whose input changes with `step` (so that moments differ from the gradients).
fn grads(m: &Net<B>, step: usize) -> GradientsParams {
    // Inputs from a formula, not the global seed, which tests running in parallel would share.
    let dev = Default::default();
    let x = Tensor::<B, 1, Int>::arange(0..30, &dev)
        .float()
        .mul_scalar(0.7 + step as f64)
        .sin()
        .mul_scalar(2.0)
        .reshape([6, 5]);
    let loss = m.b.forward(m.a.forward(x).tanh()).powf_scalar(2.0).sum();
    GradientsParams::from_grads(loss.backward(), m)
}

fn weights(m: &Net<B>) -> Vec<burn::tensor::TensorData> {
    let bias = |l: &Linear<B>| l.bias.as_ref().map(|b| b.val().into_data());
    [m.a.weight.val().into_data(), m.b.weight.val().into_data()]
        .into_iter()
        .chain(bias(&m.a))
        .chain(bias(&m.b))
        .collect()
}

/// The reference arithmetic as a kernel, standing in for a backend's on the CPU.
fn reference(slots: Vec<AdamWSlot<Inner>>, step: &AdamWStep<Inner>) -> AdamWStepped<Inner> {
    Ok(adamw_reference(slots, step))
}

fn declines(slots: Vec<AdamWSlot<Inner>>, _: &AdamWStep<Inner>) -> AdamWStepped<Inner> {
    Err((slots, "declined".into()))
}

fn norm(grads: &[FloatTensor<Inner>]) -> Result<GradNorm<Inner>, String> {
    Ok(norm_reference::<Inner>(grads))
}

/// Kernels that compute what the CPU would, through the multi-tensor path.
fn reference_kernels() -> MultiTensor<Inner> {
    MultiTensor {
        adamw: std::sync::Arc::new(reference),
        norm: std::sync::Arc::new(norm),
    }
}

/// Kernels that decline every call.
fn declining_kernels() -> MultiTensor<Inner> {
    MultiTensor {
        adamw: std::sync::Arc::new(declines),
        norm: std::sync::Arc::new(|_: &[FloatTensor<Inner>]| Err("declined".into())),
    }
}

/// Three steps of `burn_adamw` and of `fused` from the same weights, each compared after every step.
fn agree(kernels: Option<MultiTensor<Inner>>, exact: bool) {
    let mut x = net();
    let mut y = x.clone();
    let mut theirs = burn_adamw();
    let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels.clone());
    for step in 0..3 {
        let lr = 1e-2 * (step + 1) as f64;
        let (gx, gy) = (grads(&x, step), grads(&y, step));
        x = theirs.step(lr, x, gx);
        y = ours.step(lr, y, gy);
        for (a, b) in weights(&x).into_iter().zip(weights(&y)) {
            if exact {
                assert_eq!(a, b, "step {step}");
            } else {
                a.assert_approx_eq::<f32>(&b, Tolerance::rel_abs(1e-5, 1e-7));
            }
        }
    }
    let (r1, r2) = (theirs.to_record(), ours.to_record());
    assert_eq!(r1.len(), 4);
    assert_eq!(
        r1.keys().collect::<std::collections::BTreeSet<_>>(),
        r2.keys().collect()
    );
}

#[test]
fn without_a_kernel_it_is_burns_adamw() {
    agree(None, true);
}

#[test]
fn a_kernel_declining_leaves_burns_adamw() {
    agree(Some(declining_kernels()), true);
}

#[test]
fn the_reference_arithmetic_matches_burns_adamw() {
    agree(Some(reference_kernels()), false);
}

#[test]
fn records_move_between_the_two_optimizers() {
    let mut theirs = burn_adamw();
    let x = net();
    let g = grads(&x, 0);
    let x = theirs.step(1e-2, x, g);
    // burn's record continues in ours, through the reference kernel, and ours back in burn's.
    let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS)
        .with_kernels(Some(reference_kernels()))
        .load_record(theirs.to_record());
    let y = ours.step(1e-2, x.clone(), grads(&x, 1));
    let z = theirs.step(1e-2, x.clone(), grads(&x, 1));
    for (a, b) in weights(&z).into_iter().zip(weights(&y)) {
        a.assert_approx_eq::<f32>(&b, Tolerance::rel_abs(1e-5, 1e-7));
    }
    let mut back = burn_adamw().load_record(ours.to_record());
    let mut again = FusedAdamW::<Net<B>, B>::new(SETTINGS).load_record(ours.to_record());
    let (u, v) = (
        back.step(1e-2, y.clone(), grads(&y, 2)),
        again.step(1e-2, y.clone(), grads(&y, 2)),
    );
    for (a, b) in weights(&u).into_iter().zip(weights(&v)) {
        assert_eq!(a, b);
    }
}

/// The clipping factor applied while stepping equals clipping the gradients first, with and without a
/// kernel, and a bound above the norm changes nothing.
#[test]
fn a_gradient_scale_is_clipping() {
    for (kernels, exact) in [
        (None, true),
        (Some(declining_kernels()), true),
        (Some(reference_kernels()), false),
    ] {
        for bound in [0.05, 1e9] {
            let mut theirs = burn_adamw();
            let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels.clone());
            let mut x = net();
            let mut y = x.clone();
            for step in 0..2 {
                let mut g = grads(&x, step);
                let n1 = clip_grad_norm::<B, _>(&x, &mut g, bound);
                x = theirs.step(1e-2, x, g);
                let g = grads(&y, step);
                let stepped = ours.step_clipped(1e-2, y, g, bound, None);
                let n2 = stepped.norm;
                y = stepped.module;
                assert_eq!(stepped.skipped.into_scalar(), 0.0);
                if bound < 1.0 {
                    assert!(n1.clone().into_scalar() > 10.0 * bound as f32, "the bound clips");
                }
                n1.into_data()
                    .assert_approx_eq::<f32>(&n2.into_data(), Tolerance::rel_abs(1e-6, 0.0));
                for (a, b) in weights(&x).into_iter().zip(weights(&y)) {
                    if exact {
                        assert_eq!(a, b, "bound {bound}, step {step}");
                    } else {
                        a.assert_approx_eq::<f32>(&b, Tolerance::rel_abs(1e-5, 1e-7));
                    }
                }
            }
        }
    }
}

/// The first and second moments of the 2-D parameter `id`.
fn moments(o: &FusedAdamW<Net<B>, B>, id: ParamId) -> (burn::tensor::TensorData, burn::tensor::TensorData) {
    let state: AdamWState<Inner, 2> = o.to_record()[&id].clone().into_state();
    (
        state.momentum.moment_1.into_data(),
        state.momentum.moment_2.into_data(),
    )
}

/// The gradients of a loss whose input holds a NaN.
fn nan_grads(m: &Net<B>) -> GradientsParams {
    let dev = Default::default();
    let x = Tensor::<B, 2>::from_floats([[1.0, f32::NAN, 0.5, 0.0, 2.0]], &dev);
    let loss = m.b.forward(m.a.forward(x).tanh()).sum();
    GradientsParams::from_grads(loss.backward(), m)
}

/// A step whose guard or gradients are not finite leaves the weights and moments as they were (zero
/// moments at a first step), reports itself skipped, and names the parameter whose gradient is not
/// finite; the next finite step then steps from the unchanged state, with every kernel path.
#[test]
fn a_non_finite_guard_or_gradient_skips_the_step() {
    let nan = || {
        Some(Tensor::<Inner, 1>::from_floats(
            [1.0, f32::NAN],
            &Default::default(),
        ))
    };
    for kernels in [None, Some(declining_kernels()), Some(reference_kernels())] {
        let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels.clone());
        let x = net();
        // A skipped first step: the weights stay, the moments are zeros.
        let s = ours.step_clipped(1e-2, x.clone(), grads(&x, 0), 1.0, nan());
        assert_eq!(s.skipped.into_scalar(), 1.0);
        assert_eq!(weights(&s.module), weights(&x));
        assert_eq!(
            moments(&ours, x.a.weight.id)
                .0
                .iter::<f32>()
                .map(f32::abs)
                .sum::<f32>(),
            0.0
        );
        // A step, then one with NaN gradients: skipped, with the weights and records of the first.
        let y = ours.step_clipped(1e-2, s.module, grads(&x, 1), 1.0, None).module;
        let before = (weights(&y), moments(&ours, x.a.weight.id));
        let s = ours.step_clipped(1e-2, y.clone(), nan_grads(&y), 1.0, None);
        assert_eq!(s.skipped.into_scalar(), 1.0);
        assert!(s.norm.into_scalar().is_nan());
        assert_eq!((weights(&s.module), moments(&ours, x.a.weight.id)), before);
        let parts: Vec<f32> = s.parts.into_data().iter::<f32>().collect();
        let peak = ours.largest_gradient(&parts).unwrap();
        assert!(peak.non_finite > 0 && peak.name.starts_with("a."), "{peak:?}");
        // A finite step goes ahead again.
        let s = ours.step_clipped(1e-2, s.module, grads(&x, 2), 1.0, None);
        assert_eq!(s.skipped.into_scalar(), 0.0);
        assert_ne!(weights(&s.module), before.0);
    }
}

/// Two optimizers that each update half of the parameters (optimizer-state sharding), their halves put
/// together after every step, against one that updates all: the same norm and the same weights to the
/// bit, with clipping active, and each keeps moments for its own half only.
#[test]
fn shares_of_the_parameters_step_as_the_whole_does() {
    for kernels in [None, Some(declining_kernels()), Some(reference_kernels())] {
        let mut x = net();
        let ids = |l: &Linear<B>| [l.weight.id, l.bias.as_ref().map_or(l.weight.id, |b| b.id)];
        let (first, second) = (ids(&x.a), ids(&x.b));
        let mut whole = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels.clone());
        let mut halves = [first, second].map(|own| {
            let mut o = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels.clone());
            o.set_owned(Some(own.into_iter().collect()));
            o
        });
        for step in 0..3 {
            let g = grads(&x, step);
            let s = whole.step_clipped(1e-2, x.clone(), g, 0.05, None);
            let [s0, s1] =
                [0, 1].map(|k| halves[k].step_clipped(1e-2, x.clone(), grads(&x, step), 0.05, None));
            assert_eq!(s.norm.clone().into_data(), s0.norm.into_data(), "step {step}");
            assert_eq!(s.norm.into_data(), s1.norm.into_data(), "step {step}");
            // A half leaves the other half's weights as they were.
            assert_eq!(s0.module.b.weight.val().into_data(), x.b.weight.val().into_data());
            assert_eq!(s1.module.a.weight.val().into_data(), x.a.weight.val().into_data());
            let joined = Net {
                a: s0.module.a,
                b: s1.module.b,
            };
            assert_eq!(weights(&joined), weights(&s.module), "step {step}");
            x = joined;
        }
        let held = |o: &FusedAdamW<Net<B>, B>| {
            o.to_record()
                .keys()
                .copied()
                .collect::<std::collections::BTreeSet<_>>()
        };
        assert_eq!(held(&halves[0]), first.into_iter().collect());
        assert_eq!(held(&halves[1]), second.into_iter().collect());
        assert_eq!(held(&whole).len(), 4);
        // Taking a share of an optimizer that held every moment drops the others'.
        whole.set_owned(Some(second.into_iter().collect()));
        assert_eq!(held(&whole), second.into_iter().collect());
        assert_eq!(moments(&whole, second[0]), moments(&halves[1], second[0]));
    }
}
