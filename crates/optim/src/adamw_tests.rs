//! [`FusedAdamW`] against burn's `OptimizerAdaptor<AdamW>`: the same steps, the same records.

use super::*;
use crate::clip_grad_norm;
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

fn norm(grads: &[FloatTensor<Inner>]) -> Result<FloatTensor<Inner>, String> {
    Ok(norm_reference::<Inner>(grads).into_primitive().tensor())
}

/// Kernels that compute what the CPU would, through the multi-tensor path.
const REFERENCE: MultiTensor<Inner> = MultiTensor {
    adamw: reference,
    norm,
};

/// Kernels that decline every call.
const DECLINING: MultiTensor<Inner> = MultiTensor {
    adamw: declines,
    norm: |_| Err("declined".into()),
};

/// Three steps of `burn_adamw` and of `fused` from the same weights, each compared after every step.
fn agree(kernels: Option<MultiTensor<Inner>>, exact: bool) {
    let mut x = net();
    let mut y = x.clone();
    let mut theirs = burn_adamw();
    let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels);
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
    agree(Some(DECLINING), true);
}

#[test]
fn the_reference_arithmetic_matches_burns_adamw() {
    agree(Some(REFERENCE), false);
}

#[test]
fn records_move_between_the_two_optimizers() {
    let mut theirs = burn_adamw();
    let x = net();
    let g = grads(&x, 0);
    let x = theirs.step(1e-2, x, g);
    // burn's record continues in ours, through the reference kernel, and ours back in burn's.
    let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS)
        .with_kernels(Some(REFERENCE))
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
    for (kernels, exact) in [(None, true), (Some(DECLINING), true), (Some(REFERENCE), false)] {
        for bound in [0.05, 1e9] {
            let mut theirs = burn_adamw();
            let mut ours = FusedAdamW::<Net<B>, B>::new(SETTINGS).with_kernels(kernels);
            let mut x = net();
            let mut y = x.clone();
            for step in 0..2 {
                let mut g = grads(&x, step);
                let n1 = clip_grad_norm::<B, _>(&x, &mut g, bound);
                x = theirs.step(1e-2, x, g);
                let g = grads(&y, step);
                let n2;
                (y, n2) = ours.step_clipped(1e-2, y, g, bound);
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
