//! Mixed precision: bf16 products with f32 master weights.

use super::*;
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamWConfig, GradientsParams, Optimizer};
use burn::tensor::DType;

fn loss(m: &Backbone<A>, toks: Tensor<A, 3, Int>) -> Tensor<A, 1> {
    m.loss(toks, 1.0).unwrap().total
}

#[test]
fn bf16_loss_is_close_to_f32_and_training_keeps_f32_parameters() {
    let (b, f, n) = (2, 3, spec().n);
    let ids = tokens(&spec(), b, f, 31);
    // The same parameters in both: burn initialises parameters lazily (and a clone on its own), and tests
    // share the backend's seed, so both models load one materialised record.
    let full = model_in::<A>(Precision::F32);
    let full = model_in::<A>(Precision::F32).load_record(full.into_record());
    let half = model_in::<A>(Precision::Bf16).load_record(full.clone().into_record());
    let l_full = loss(&full, tensor::<A>(&ids, b, f, n));
    let l_half = loss(&half, tensor::<A>(&ids, b, f, n));
    assert_eq!(l_half.dtype(), DType::F32);
    let (x, y) = (l_full.clone().into_scalar(), l_half.clone().into_scalar());
    let rel = ((x - y) / x).abs();
    // Only the rounding of the products differs, by about bf16's 2⁻⁸.
    assert!(
        rel > 1e-7 && rel < 1e-2,
        "losses {x} (f32) and {y} (bf16): relative difference {rel}"
    );

    let grads = GradientsParams::from_grads(l_half.backward(), &half);
    let mut optim = AdamWConfig::new().init();
    let stepped = optim.step(1e-3, half.clone(), grads);
    // Every parameter is still f32 after a step (master weights), and the step moved them.
    let (dtypes, moved) = (Dtypes::of(&stepped), changed(&half, &stepped));
    assert!(
        dtypes.0 > 0 && dtypes.0 == dtypes.1,
        "{} of {} parameters are f32",
        dtypes.1,
        dtypes.0
    );
    assert!(moved > 0, "no parameter moved");
}

/// (parameters, f32 parameters) of a module.
struct Dtypes(usize, usize);

impl Dtypes {
    fn of(m: &Backbone<A>) -> Self {
        let mut v = Dtypes(0, 0);
        m.visit(&mut v);
        v
    }
}

impl ModuleVisitor<A> for Dtypes {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
        self.0 += 1;
        self.1 += usize::from(param.val().dtype() == DType::F32);
    }
}

/// How many parameter tensors differ between two modules of the same structure.
fn changed(a: &Backbone<A>, b: &Backbone<A>) -> usize {
    struct Collect(Vec<Vec<f32>>);
    impl ModuleVisitor<A> for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
            self.0.push(param.val().into_data().iter::<f32>().collect());
        }
    }
    let (mut x, mut y) = (Collect(Vec::new()), Collect(Vec::new()));
    a.visit(&mut x);
    b.visit(&mut y);
    x.0.iter().zip(&y.0).filter(|(p, q)| p != q).count()
}
