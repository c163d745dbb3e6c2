//! The products of the linear layers and output heads on a named matmul kernel.
//!
//! Without burn's `autotune` build every product runs one default kernel (cubek's simple cyclic CMMA).
//! `umgen-kernel-bench matmul` timed the kernels cubek offers on the `small` training step's shapes (H200):
//! `specialized_tma_mma` ran the projections, heads and weight gradients 1.7–2.8× faster than the default
//! in f32 and 2.3–3.7× in bf16, while two other kernels gave wrong results on the weight-gradient shape,
//! so letting autotuning pick by time alone is not safe either. Training on CUDA therefore routes each
//! linear layer's product through [`named_autodiff`], a custom autodiff operation whose forward product
//! and both gradient products go to [`NamedMatmul::named_matmul`]; on CUDA that launches the one kernel
//! named here and falls back to burn's default kernel, counted and logged, on any shape or format it does
//! not take (`matmul/cuda.rs`). `umgen-kernel-bench linear` checks the operation against burn's own path on the
//! GPU, forward and gradients.
//!
//! With [`Precision::Bf16`] the operation casts its operands itself: it saves them in bf16 (half the
//! memory of burn's path, which saves f32 inputs before its cast), and every product, gradients included,
//! reads bf16 and writes f32, where burn's differentiable cast would compute the gradients in bf16. A
//! caller whose result (or input gradient) only feeds another bf16 operation asks for it in bf16
//! ([`Written`]): the MLP's first product writes its pre-activation in bf16 for the bias + GELU kernel,
//! and the second product writes the hidden activation's gradient in bf16 for that kernel's backward pass,
//! as PyTorch's bf16 autocast does; the product still accumulates in f32.
//!
//! On the CPU (`Autodiff<Flex>`) the operation runs burn's one product, so CPU training checks its gradients;
//! any other backend, and [`MatmulKernel::Burn`], keep burn's `matmul`.

use crate::dispatch::same;
use crate::format::Precision;
use crate::format::float;
use crate::format::operand;
use crate::kernels::Kernels;
pub use crate::kernels::MatmulKernel;
pub use biased::{BiasedFn, biased_autodiff, biased_for};
pub(crate) use biased::{Weight, backward_biased};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{FloatDType, Tensor};

/// Finishes the custom autodiff operation `op` on checkpointing strategy `C` with its `parents`: the
/// result `y`, tracked with `state` where any parent is. A macro because an operation whose number of
/// parents varies (a linear layer with or without the residual it joins) names each arm's parents, and
/// burn's node type is private to its autodiff crate.
macro_rules! finish_op {
    ($c:ty, $op:expr, $parents:expr, $state:expr, $y:expr) => {
        match $op.prepare::<$c>($parents).compute_bound().stateful() {
            burn::backend::autodiff::ops::OpsKind::Tracked(prep) => prep.finish($state, $y),
            burn::backend::autodiff::ops::OpsKind::UnTracked(prep) => prep.finish($y),
        }
    };
}
pub(crate) use finish_op;

mod biased;
#[cfg(feature = "cuda")]
mod cublas;
#[cfg(feature = "cuda")]
mod cublaslt;
#[cfg(feature = "cuda")]
mod cuda;
#[cfg(feature = "cuda")]
pub use cuda::{fallbacks, launch_kernel};

/// A backend that can multiply two `[m, k] × [k, n]` matrices of one float format (either may be a
/// transposed view) into a result of a given format, accumulating in f32, on a kernel of its choosing.
pub trait NamedMatmul: Backend {
    /// `lhs · rhs` in `out`, on the kernel `k` names.
    fn named_matmul(
        lhs: FloatTensor<Self>,
        rhs: FloatTensor<Self>,
        out: FloatDType,
        k: &Kernels,
    ) -> FloatTensor<Self>;

    /// `lhs · rhs + bias + add` in `out`: `bias` `[n]` added to every row and `add` `[m, n]` summed, in the
    /// product's epilogue where the kernel has one (cuBLASLt on CUDA). By default [`epilogue_decomposed`]:
    /// the product, then burn's additions.
    fn named_matmul_epilogue(
        lhs: FloatTensor<Self>,
        rhs: FloatTensor<Self>,
        (bias, add): (Option<FloatTensor<Self>>, Option<FloatTensor<Self>>),
        out: FloatDType,
        k: &Kernels,
    ) -> FloatTensor<Self> {
        epilogue_decomposed::<Self>(lhs, rhs, (bias, add), out, k)
    }
}

/// [`NamedMatmul::named_matmul_epilogue`] as the product and burn's additions: a 16-bit result with a bias
/// only is written in its format and the bias added in it (one pass over the half-width result); anything
/// else is summed in f32 and then cast to `out`.
pub fn epilogue_decomposed<B: NamedMatmul>(
    lhs: FloatTensor<B>,
    rhs: FloatTensor<B>,
    (bias, add): (Option<FloatTensor<B>>, Option<FloatTensor<B>>),
    out: FloatDType,
    k: &Kernels,
) -> FloatTensor<B> {
    if add.is_none() && out != FloatDType::F32 {
        let y = float::<B, 2>(B::named_matmul(lhs, rhs, out, k));
        let y = match bias {
            Some(b) => y + float::<B, 1>(b).cast(out).unsqueeze::<2>(),
            None => y,
        };
        return y.into_primitive().tensor();
    }
    let y = float::<B, 2>(B::named_matmul(lhs, rhs, FloatDType::F32, k));
    added(y, (bias, add), out).into_primitive().tensor()
}

/// An f32 product `y` plus `bias` and `add`, summed in f32, then cast to `out`: an epilogue's additions as
/// burn operations (on any backend: the CUDA fallback runs them on cubecl's).
pub(crate) fn added<B: Backend>(
    y: Tensor<B, 2>,
    (bias, add): (Option<FloatTensor<B>>, Option<FloatTensor<B>>),
    out: FloatDType,
) -> Tensor<B, 2> {
    let mut y = y;
    if let Some(b) = bias {
        y = y + float::<B, 1>(b).cast(FloatDType::F32).unsqueeze::<2>();
    }
    if let Some(a) = add {
        y = y + float::<B, 2>(a).cast(FloatDType::F32);
    }
    y.cast(out)
}

/// The CPU backend has one kernel: burn's product, cast to the result's format. It lets the CPU tests
/// check the operation's gradients and casts.
impl NamedMatmul for burn::backend::Flex {
    fn named_matmul(
        lhs: FloatTensor<Self>,
        rhs: FloatTensor<Self>,
        out: FloatDType,
        _: &Kernels,
    ) -> FloatTensor<Self> {
        float::<Self, 2>(lhs)
            .matmul(float(rhs))
            .cast(FloatDType::F32)
            .cast(out)
            .into_primitive()
            .tensor()
    }
}

/// The formats a named product writes: its result, and its input's gradient in the backward pass (the
/// weight's gradient is always f32, for the optimizer).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Written {
    /// The result's format.
    pub out: FloatDType,
    /// The format of the input's gradient.
    pub dx: FloatDType,
}

impl Written {
    /// f32 results and gradients: what every product writes unless its caller knows better.
    pub const F32: Self = Self {
        out: FloatDType::F32,
        dx: FloatDType::F32,
    };
}

/// `x · w` for `x: [m, k]` and `w: [k, n]`, the product in `p`'s format, the result and `x`'s gradient in
/// the [`Written`] formats, on the kernel the [`Kernels`] name.
pub type ProductFn<B> = fn(Tensor<B, 2>, Tensor<B, 2>, Precision, Written, &Kernels) -> Tensor<B, 2>;

/// [`named_autodiff`] as a function on `B` when `B` is one of the autodiff backends this workspace trains on
/// (CUDA, or the CPU's `Flex`, where it runs burn's product) and `k` does not choose [`MatmulKernel::Burn`];
/// `None` otherwise (the caller then uses burn's `matmul`).
pub fn named_for<B: Backend>(k: &Kernels) -> Option<ProductFn<B>> {
    if k.matmul == MatmulKernel::Burn {
        return None;
    }
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

/// `named_autodiff` on `Autodiff<I, C>` (either checkpointing strategy), if that is `B`.
fn on<B: Backend, I: NamedMatmul>() -> Option<ProductFn<B>> {
    let plain: ProductFn<Autodiff<I, NoCheckpointing>> = named_autodiff::<I, NoCheckpointing>;
    let balanced: ProductFn<Autodiff<I, BalancedCheckpointing>> = named_autodiff::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

/// `a · b` on `B`'s named kernel, f32.
pub(crate) fn product<B: NamedMatmul>(a: Tensor<B, 2>, b: Tensor<B, 2>, k: &Kernels) -> Tensor<B, 2> {
    product_in(a, b, FloatDType::F32, k)
}

/// `a · b` on `B`'s named kernel, in `out`.
pub(crate) fn product_in<B: NamedMatmul>(
    a: Tensor<B, 2>,
    b: Tensor<B, 2>,
    out: FloatDType,
    k: &Kernels,
) -> Tensor<B, 2> {
    float(B::named_matmul(
        a.into_primitive().tensor(),
        b.into_primitive().tensor(),
        out,
        k,
    ))
}

/// `a · b + bias + add` on `B`'s named kernel, in `out` ([`NamedMatmul::named_matmul_epilogue`]).
pub(crate) fn product_epilogue<B: NamedMatmul>(
    a: Tensor<B, 2>,
    b: Tensor<B, 2>,
    (bias, add): (Option<Tensor<B, 1>>, Option<Tensor<B, 2>>),
    out: FloatDType,
    k: &Kernels,
) -> Tensor<B, 2> {
    let prim = |t: Tensor<B, 2>| t.into_primitive().tensor();
    float(B::named_matmul_epilogue(
        prim(a),
        prim(b),
        (bias.map(|t| t.into_primitive().tensor()), add.map(prim)),
        out,
        k,
    ))
}

#[derive(Debug)]
struct Product;

impl<B: NamedMatmul> Backward<B, 2> for Product {
    /// `x` and `w` in the products' format, that format, the input gradient's, the kernels.
    type State = (FloatTensor<B>, FloatTensor<B>, Precision, FloatDType, Kernels);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [nx, nw] = ops.parents;
        let (x, w, p, dx_format, k) = ops.state;
        let dy = operand(float::<B, 2>(grads.consume::<B>(&ops.node)), p);
        if let Some(node) = nx {
            let dx = product_in(dy.clone(), float::<B, 2>(w).transpose(), dx_format, &k);
            grads.register::<B>(node.id, dx.into_primitive().tensor());
        }
        if let Some(node) = nw {
            let dw = product(float::<B, 2>(x).transpose(), dy, &k);
            grads.register::<B>(node.id, dw.into_primitive().tensor());
        }
    }
}

/// `x · w` on `Autodiff<I, C>` with every product (forward, input gradient, weight gradient) on `I`'s
/// named kernel, operands in `p`'s format, the result and the input's gradient in the `written` formats
/// and the weight's gradient f32. `x: [m, k]`, `w: [k, n]`.
pub fn named_autodiff<I: NamedMatmul, C: CheckpointStrategy>(
    x: Tensor<Autodiff<I, C>, 2>,
    w: Tensor<Autodiff<I, C>, 2>,
    p: Precision,
    written: Written,
    k: &Kernels,
) -> Tensor<Autodiff<I, C>, 2> {
    let (x, w) = (x.into_primitive().tensor(), w.into_primitive().tensor());
    let prep = Product
        .prepare::<C>([x.node.clone(), w.node.clone()])
        .compute_bound()
        .stateful();
    let (xi, wi) = (
        operand(float::<I, 2>(x.primitive), p),
        operand(float::<I, 2>(w.primitive), p),
    );
    let y = product_in(xi.clone(), wi.clone(), written.out, k)
        .into_primitive()
        .tensor();
    let y = match prep {
        OpsKind::Tracked(prep) => prep.finish(
            (
                xi.into_primitive().tensor(),
                wi.into_primitive().tensor(),
                p,
                written.dx,
                *k,
            ),
            y,
        ),
        OpsKind::UnTracked(prep) => prep.finish(y),
    };
    float(y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::Flex;
    use burn::tensor::{DType, Distribution};

    type A = Autodiff<Flex>;

    fn rel(a: Tensor<Flex, 2>, b: Tensor<Flex, 2>) -> f32 {
        let scale = b.clone().abs().max().into_scalar();
        (a - b).abs().max().into_scalar() / scale
    }

    /// Output and both gradients of `x · w` (under a non-uniform upstream gradient) on `f`.
    fn run(
        f: impl Fn(Tensor<A, 2>, Tensor<A, 2>) -> Tensor<A, 2>,
        x: &Tensor<Flex, 2>,
        w: &Tensor<Flex, 2>,
        up: &Tensor<Flex, 2>,
    ) -> [Tensor<Flex, 2>; 3] {
        let xa = Tensor::<A, 2>::from_inner(x.clone()).require_grad();
        let wa = Tensor::<A, 2>::from_inner(w.clone()).require_grad();
        let y = f(xa.clone(), wa.clone());
        // The upstream gradient in the result's format (a bf16 result multiplies bf16 values).
        let up = Tensor::<A, 2>::from_inner(up.clone()).cast(crate::format::float_format(y.dtype()));
        let g = (y.clone() * up).sum().backward();
        let (dx, dw) = (xa.grad(&g).expect("dx"), wa.grad(&g).expect("dw"));
        [y.inner(), dx, dw]
    }

    #[test]
    fn output_and_gradients_match_burns_matmul() {
        let dev = Default::default();
        let n = Distribution::Normal(0.0, 1.0);
        for (m, k, nn) in [(7, 5, 3), (33, 48, 17)] {
            let x = Tensor::<Flex, 2>::random([m, k], n, &dev);
            let w = Tensor::<Flex, 2>::random([k, nn], n, &dev);
            let up = Tensor::<Flex, 2>::random([m, nn], n, &dev);
            let reference = run(|x, w| x.matmul(w), &x, &w, &up);
            let full = run(
                |x, w| named_autodiff(x, w, Precision::F32, Written::F32, &Kernels::default()),
                &x,
                &w,
                &up,
            );
            for (name, (a, b)) in ["y", "dx", "dw"]
                .iter()
                .zip(full.into_iter().zip(reference.clone()))
            {
                assert_eq!(a.dims(), b.dims(), "{name}");
                let err = rel(a, b);
                assert!(err < 1e-6, "{name} at {m}×{k}×{nn}: relative error {err}");
            }
            // bf16 operands: every result f32, within bf16's resolution of f32 but not equal to it.
            let half = run(
                |x, w| named_autodiff(x, w, Precision::Bf16, Written::F32, &Kernels::default()),
                &x,
                &w,
                &up,
            );
            for (name, (a, b)) in ["y", "dx", "dw"].iter().zip(half.into_iter().zip(reference)) {
                assert_eq!(a.dtype(), DType::F32, "{name}");
                let err = rel(a, b);
                assert!(
                    err > 1e-6 && err < 2e-2,
                    "{name} at {m}×{k}×{nn} in bf16: relative error {err}"
                );
            }
        }
    }

    /// A product written in bf16 is the f32 result rounded, its input's gradient (asked for in bf16) is the
    /// f32 gradient rounded, and the weight's gradient stays f32 and unchanged.
    #[test]
    fn bf16_written_results_are_the_f32_ones_rounded() {
        let dev = Default::default();
        let n = Distribution::Normal(0.0, 1.0);
        let x = Tensor::<Flex, 2>::random([9, 24], n, &dev);
        let w = Tensor::<Flex, 2>::random([24, 7], n, &dev);
        let up = Tensor::<Flex, 2>::random([9, 7], n, &dev).cast(FloatDType::BF16);
        let f32s = run(
            |x, w| named_autodiff(x, w, Precision::Bf16, Written::F32, &Kernels::default()),
            &x,
            &w,
            &up,
        );
        let bf16 = Written {
            out: FloatDType::BF16,
            dx: FloatDType::BF16,
        };
        let [y, dx, dw] = run(
            |x, w| named_autodiff(x, w, Precision::Bf16, bf16, &Kernels::default()),
            &x,
            &w,
            &up,
        );
        assert_eq!(
            [y.dtype(), dx.dtype(), dw.dtype()],
            [DType::BF16, DType::BF16, DType::F32]
        );
        let [y32, dx32, dw32] = f32s;
        // bf16 to f32 is exact: equal f32 values are equal bf16 values.
        let rounded = |t: Tensor<Flex, 2>| {
            let data = t.cast(FloatDType::BF16).cast(FloatDType::F32).into_data();
            data.to_vec::<f32>().expect("f32 values")
        };
        assert_eq!(rounded(y32), rounded(y));
        assert_eq!(rounded(dx32), rounded(dx));
        assert_eq!(rel(dw, dw32), 0.0);
    }

    #[test]
    fn untracked_inputs_get_no_gradient_and_only_training_backends_dispatch() {
        let dev = Default::default();
        let x = Tensor::<A, 2>::ones([2, 3], &dev);
        let w = Tensor::<A, 2>::ones([3, 4], &dev).require_grad();
        let g = named_autodiff(
            x.clone(),
            w.clone(),
            Precision::F32,
            Written::F32,
            &Kernels::default(),
        )
        .sum()
        .backward();
        assert!(x.grad(&g).is_none());
        // Each of the 3 × 4 weights meets both rows of ones.
        assert_eq!(
            w.grad(&g).expect("dw").into_data().to_vec::<f32>().expect("f32"),
            vec![2.0; 12]
        );
        let k = Kernels::default();
        assert!(named_for::<A>(&k).is_some() && named_for::<Flex>(&k).is_none());
        let burn = Kernels {
            matmul: MatmulKernel::Burn,
            ..k
        };
        assert!(
            named_for::<A>(&burn).is_none(),
            "the `burn` choice keeps burn's product"
        );
    }
}
