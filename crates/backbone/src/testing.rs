//! What the layer tests share: the CPU autodiff backend, parameters and inputs drawn from fixed seeds,
//! parameter gradients and relative errors.
#![allow(clippy::expect_used)]

use burn::backend::autodiff::grads::Gradients;
use burn::backend::{Autodiff, Flex};
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Tensor;

/// The CPU's autodiff backend the tests train on.
pub type A = Autodiff<Flex>;

/// Every parameter gradient of `m` in `grads`, in visiting order.
pub fn param_grads<M: Module<A>>(m: &M, grads: &Gradients) -> Vec<Tensor<Flex, 1>> {
    struct Collect<'a>(&'a Gradients, Vec<Tensor<Flex, 1>>);
    impl ModuleVisitor<A> for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
            let g = param.val().grad(self.0).expect("every parameter has a gradient");
            self.1.push(g.flatten(0, D - 1));
        }
    }
    let mut c = Collect(grads, Vec::new());
    m.visit(&mut c);
    c.1
}

/// Largest difference relative to the largest magnitude of `b`.
pub fn rel<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>) -> f32 {
    let scale = b.clone().abs().max().into_scalar().max(1e-12);
    (a - b).abs().max().into_scalar() / scale
}

/// A tensor of `dims` with normal values (`shift` + `scale` · N(0, 1)) drawn from `seed` alone, not from
/// the backend's random generator, which tests running in parallel share.
pub fn normal<const D: usize>(dims: [usize; D], seed: u64, scale: f32, shift: f32) -> Tensor<Flex, D> {
    let mut state = seed ^ 0x9e37_79b9_7f4a_7c15;
    let mut uniform = move || {
        // splitmix64, its top 24 bits as a uniform number in (0, 1).
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32 + 0.5 / (1u64 << 24) as f32
    };
    let n: usize = dims.iter().product();
    let values: Vec<f32> = (0..n)
        .map(|_| {
            let (u, v) = (uniform(), uniform());
            shift + scale * (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
        })
        .collect();
    Tensor::from_data(burn::tensor::TensorData::new(values, dims), &Default::default())
}

/// `m` with every parameter drawn from `seed` alone ([`normal`]), spread about as burn's initialisation
/// plus a noise of 0.2 would spread them: norms' scales around 1, shifts, biases and weights around 0
/// with a spread of 0.22 (so that no formula's scale or shift is the identity).
pub fn seeded<M: Module<A>>(m: M, seed: u64) -> M {
    struct Draw(u64);
    impl ModuleMapper<A> for Draw {
        fn map_float<const D: usize>(&mut self, param: Param<Tensor<A, D>>) -> Param<Tensor<A, D>> {
            self.0 += 1;
            let seed = self.0;
            param.map(|t| {
                // A norm's scale starts at 1, everything else around 0.
                let ones = t.clone().inner().equal_elem(1.0).all().into_scalar();
                let shift = if D == 1 && ones { 1.0 } else { 0.0 };
                Tensor::from_inner(normal(t.dims(), seed, 0.22, shift)).require_grad()
            })
        }
    }
    m.map(&mut Draw(seed << 16))
}
