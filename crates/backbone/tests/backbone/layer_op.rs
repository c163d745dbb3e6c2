//! Attention layers as one operation each, recomputed (`train.kernels.recompute`) or keeping their
//! activations (`train.kernels.layer = "fused"`): the whole model's loss and gradients as through burn's
//! autodiff.

use super::*;
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use umgen_backbone::{Kernels, LossOptions};
use umgen_ops::kernels::LayerKernel;
use umgen_ops::layer::{layers_kept, layers_recomputed};

/// Every parameter gradient of `m`, flattened, in visiting order; `None` for a parameter without one.
fn grads(m: &Backbone<A>, g: &GradientsParams) -> Vec<Option<Tensor<F, 1>>> {
    struct Collect<'a>(&'a GradientsParams, Vec<Option<Tensor<F, 1>>>);
    impl ModuleVisitor<A> for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
            let g = self.0.get::<F, D>(param.id);
            self.1.push(g.map(|g| g.flatten(0, D - 1)));
        }
    }
    let mut c = Collect(g, Vec::new());
    m.visit(&mut c);
    c.1
}

#[test]
fn one_op_layers_give_the_loss_and_gradients_of_autodiffs() {
    let (b, f, n) = (2, 3, spec().n);
    let ids = tokens(&spec(), b, f, 5);
    let m = model::<A>();
    let m = model::<A>().load_record(m.into_record());
    let run = |recompute: bool, layer: LayerKernel| {
        let opts = LossOptions {
            ego_weight: 1.0,
            prior_drop: 0.0,
            ordinal_sigma: 0.0,
            kernels: Kernels {
                recompute,
                layer,
                ..Kernels::DEFAULT
            },
        };
        let l = m.loss_with(tensor::<A>(&ids, b, f, n), opts).unwrap().total;
        let g = GradientsParams::from_grads(l.backward(), &m);
        (l.into_scalar(), grads(&m, &g))
    };
    let (l0, g0) = run(false, LayerKernel::Burn);
    let paths = [
        (true, LayerKernel::Burn, layers_recomputed as fn() -> u64),
        (false, LayerKernel::Fused, layers_kept),
    ];
    for (recompute, layer, count) in paths {
        let before = count();
        let (l1, g1) = run(recompute, layer);
        // Two TAR blocks of two layers and two OAR layers took the operation.
        assert!(count() >= before + 6, "recompute {recompute}");
        assert!(
            ((l1 - l0) / l0).abs() < 1e-5,
            "recompute {recompute}: losses {l0} and {l1}"
        );
        assert_eq!(g0.len(), g1.len());
        for (i, (a, b)) in g1.into_iter().zip(g0.clone()).enumerate() {
            // A parameter has a gradient on both paths or on neither (the ego module is off in this model).
            let (Some(a), Some(b)) = (a.clone(), b.clone()) else {
                assert_eq!(a.is_some(), b.is_some(), "parameter tensor {i}");
                continue;
            };
            let scale = b.clone().abs().max().into_scalar().max(1e-12);
            let e = (a - b).abs().max().into_scalar() / scale;
            assert!(
                e < 1e-4,
                "recompute {recompute}: parameter tensor {i}: relative error {e}"
            );
        }
    }
}
