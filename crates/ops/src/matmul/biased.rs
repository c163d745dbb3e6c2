//! A linear layer `x · w + b` (and, where given, `+ add`: the residual stream it joins) as one autodiff
//! operation on the named kernel, the bias and the added rows summed by the product's epilogue
//! ([`NamedMatmul::named_matmul_epilogue`]: cuBLASLt's on CUDA).
//!
//! The layer was a product ([`super::named_autodiff`]) followed by `rows::add_for`'s bias add, and the
//! residual stream's add after that: each a pass over the result. The backward pass is theirs together:
//! the incoming gradient is the added rows' as it is, its column sums are the bias's, written with the
//! products' bf16 copy in one pass (`rows::sum_cast`), and the products' gradients follow.

use super::{NamedMatmul, Written, product, product_epilogue, product_in};
use crate::dispatch::same;
use crate::format::{Precision, float, operand};
use crate::kernels::Kernels;
use burn::backend::Autodiff;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{FloatDType, Tensor};

/// A linear layer's input `x: [m, k]`, weight `w: [k, n]` and bias `b: [n]`.
pub type Layer<B> = (Tensor<B, 2>, Tensor<B, 2>, Tensor<B, 1>);

/// `x · w + b + add` (`add: [m, n]`, f32, where given), the product in `p`'s format, the result and `x`'s
/// gradient in the [`Written`] formats.
pub type BiasedFn<B> = fn(Layer<B>, Option<Tensor<B, 2>>, Precision, Written, &Kernels) -> Tensor<B, 2>;

/// [`biased_autodiff`] as a function on `B`, under the same conditions as [`super::named_for`].
pub fn biased_for<B: Backend>(k: &Kernels) -> Option<BiasedFn<B>> {
    super::named_for::<B>(k)?;
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

fn on<B: Backend, I: NamedMatmul>() -> Option<BiasedFn<B>> {
    let plain: BiasedFn<Autodiff<I, NoCheckpointing>> = biased_autodiff::<I, NoCheckpointing>;
    let balanced: BiasedFn<Autodiff<I, BalancedCheckpointing>> = biased_autodiff::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// The backward pass: `N` = 3 parents (x, w, b), or 4 with the added rows.
#[derive(Debug)]
struct Biased<const N: usize>;

/// `x` in the products' format, and the [`Weight`].
type State<B> = (FloatTensor<B>, Weight<B>);

/// What a biased product's backward pass needs besides its input: the weight in the products' format,
/// that format, the input gradient's, the kernels.
pub(crate) type Weight<B> = (FloatTensor<B>, Precision, FloatDType, Kernels);

impl<B: NamedMatmul, const N: usize> Backward<B, N> for Biased<N> {
    type State = State<B>;

    fn backward(self, ops: Ops<Self::State, N>, grads: &mut Gradients, _: &mut Checkpointer) {
        let ids = ops.parents.map(|p| p.map(|node| node.id));
        let (x, weight) = ops.state;
        let g = grads.consume::<B>(&ops.node);
        backward_biased::<B>(&ids, g, weight, || float(x), grads);
    }
}

/// Registers the gradients of a biased product's parents `ids` (its input, its weight, its bias, and the
/// added rows where there are four) from the result's gradient `g`. `input` gives the product's input in
/// the products' format; it is called only where the weight asks for a gradient (the MLP's second product
/// recomputes it there).
pub(crate) fn backward_biased<B: NamedMatmul>(
    ids: &[Option<NodeId>],
    g: FloatTensor<B>,
    (w, p, dx_format, k): Weight<B>,
    input: impl FnOnce() -> Tensor<B, 2>,
    grads: &mut Gradients,
) {
    let g = float::<B, 2>(g);
    if let Some(Some(id)) = ids.get(3) {
        grads.register::<B>(*id, g.clone().cast(FloatDType::F32).into_primitive().tensor());
    }
    // The bias's sum and the products' operand in one pass.
    let (dy, db) = crate::rows::sum_cast(g, p.operand_dtype());
    let dy = operand(dy, p);
    if let Some(Some(id)) = ids.get(2) {
        grads.register::<B>(*id, db.into_primitive().tensor());
    }
    if let Some(Some(id)) = ids.first() {
        let dx = product_in(dy.clone(), float::<B, 2>(w).transpose(), dx_format, &k);
        grads.register::<B>(*id, dx.into_primitive().tensor());
    }
    if let Some(Some(id)) = ids.get(1) {
        let dw = product(input().transpose(), dy, &k);
        grads.register::<B>(*id, dw.into_primitive().tensor());
    }
}

/// `x · w + b (+ add)` on `Autodiff<I, C>` with every product on `I`'s named kernel and the bias and
/// added rows in the forward product's epilogue.
pub fn biased_autodiff<I: NamedMatmul, C: CheckpointStrategy>(
    (x, w, b): Layer<Autodiff<I, C>>,
    add: Option<Tensor<Autodiff<I, C>, 2>>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 2> {
    let (x, w, b) = (
        x.into_primitive().tensor(),
        w.into_primitive().tensor(),
        b.into_primitive().tensor(),
    );
    let add = add.map(|a| a.into_primitive().tensor());
    let (xi, wi) = (
        operand(float::<I, 2>(x.primitive), p),
        operand(float::<I, 2>(w.primitive), p),
    );
    let y = product_epilogue(
        xi.clone(),
        wi.clone(),
        (
            Some(float(b.primitive)),
            add.as_ref().map(|a| float(a.primitive.clone())),
        ),
        written.out,
        k,
    )
    .into_primitive()
    .tensor();
    let state = (
        xi.into_primitive().tensor(),
        (wi.into_primitive().tensor(), p, written.dx, *k),
    );
    let out = match add {
        Some(a) => finish_op!(C, Biased::<4>, [x.node, w.node, b.node, a.node], state, y),
        None => finish_op!(C, Biased::<3>, [x.node, w.node, b.node], state, y),
    };
    float(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::Flex;
    use burn::tensor::{DType, Distribution};

    type A = Autodiff<Flex>;

    fn rel<const D: usize>(a: Tensor<Flex, D>, b: Tensor<Flex, D>) -> f32 {
        let scale = b.clone().abs().max().into_scalar();
        (a - b).abs().max().into_scalar() / scale
    }

    /// Output and every gradient (x, w, b and the added rows) under a non-uniform upstream gradient, against
    /// burn's own `x · w + b + add`.
    #[test]
    fn output_and_gradients_match_burns_operations() {
        let dev = Default::default();
        let n = Distribution::Normal(0.0, 1.0);
        let (x, w) = (
            Tensor::<Flex, 2>::random([37, 24], n, &dev),
            Tensor::<Flex, 2>::random([24, 9], n, &dev),
        );
        let b = Tensor::<Flex, 1>::random([9], n, &dev);
        let (add, up) = (
            Tensor::<Flex, 2>::random([37, 9], n, &dev),
            Tensor::<Flex, 2>::random([37, 9], n, &dev),
        );
        let run = |ours: bool, with_add: bool| {
            let track = |t: &Tensor<Flex, 2>| Tensor::<A, 2>::from_inner(t.clone()).require_grad();
            let (xa, wa, aa) = (track(&x), track(&w), track(&add));
            let ba = Tensor::<A, 1>::from_inner(b.clone()).require_grad();
            let added = with_add.then(|| aa.clone());
            let y = if ours {
                let k = Kernels::default();
                biased_autodiff(
                    (xa.clone(), wa.clone(), ba.clone()),
                    added,
                    Precision::F32,
                    Written::F32,
                    &k,
                )
            } else {
                let y = xa.clone().matmul(wa.clone()) + ba.clone().unsqueeze::<2>();
                added.map_or(y.clone(), |a| y + a)
            };
            let g = (y.clone() * Tensor::from_inner(up.clone())).sum().backward();
            let grad = |t: &Tensor<A, 2>| t.grad(&g);
            (y.inner(), grad(&xa), grad(&wa), ba.grad(&g), grad(&aa))
        };
        for with_add in [false, true] {
            let (y, dx, dw, db, da) = run(true, with_add);
            let (ry, rdx, rdw, rdb, rda) = run(false, with_add);
            let some = |t: Option<Tensor<Flex, 2>>| t.expect("a gradient");
            assert!(rel(y, ry) < 1e-5, "y (add: {with_add})");
            assert!(rel(some(dx), some(rdx)) < 1e-5, "dx (add: {with_add})");
            assert!(rel(some(dw), some(rdw)) < 1e-5, "dw (add: {with_add})");
            assert!(
                rel(db.expect("db"), rdb.expect("db")) < 1e-5,
                "db (add: {with_add})"
            );
            match (da, rda) {
                (Some(a), Some(r)) => assert!(with_add && rel(a, r) < 1e-6, "the added rows' gradient"),
                (None, None) => assert!(!with_add),
                _ => panic!("the added rows' gradient exists on one side only (add: {with_add})"),
            }
        }
    }

    /// In bf16 the result is written in bf16, `x`'s gradient in the asked format and the bias's in f32, all
    /// within bf16's resolution of f32.
    #[test]
    fn bf16_results_are_within_bf16_of_f32() {
        let dev = Default::default();
        let n = Distribution::Normal(0.0, 1.0);
        let x = Tensor::<A, 2>::random([16, 32], n, &dev).require_grad();
        let w = Tensor::<A, 2>::random([32, 8], n, &dev).require_grad();
        let b = Tensor::<A, 1>::random([8], n, &dev).require_grad();
        let written = Written {
            out: FloatDType::BF16,
            dx: FloatDType::BF16,
        };
        let k = Kernels::default();
        let y = biased_autodiff(
            (x.clone(), w.clone(), b.clone()),
            None,
            Precision::Bf16,
            written,
            &k,
        );
        assert_eq!(y.dtype(), DType::BF16);
        let reference = x.clone().inner().matmul(w.clone().inner()) + b.clone().inner().unsqueeze::<2>();
        let err = rel(y.clone().inner().cast(FloatDType::F32), reference);
        assert!(err > 0.0 && err < 2e-2, "relative error {err}");
        let g = y.cast(FloatDType::F32).sum().backward();
        assert_eq!(x.grad(&g).expect("dx").dtype(), DType::BF16);
        let db = b.grad(&g).expect("db");
        assert_eq!(db.dtype(), DType::F32);
        // Each bias sees every one of the 16 rows once.
        assert!(rel(db, Tensor::<Flex, 1>::full([8], 16.0, &dev)) < 1e-6);
    }
}
