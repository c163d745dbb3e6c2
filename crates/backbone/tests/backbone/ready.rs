//! The ready points: each TAR and OAR block's point runs once in the backward pass, deepest block first,
//! with every gradient of its block complete.

use crate::{A, model, spec, tokens};
use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::{Int, Tensor, TensorData};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use umgen_backbone::LossOptions;
use umgen_ops::ready::{ReadyHook, ReadyPoints};

/// Every float parameter's gradient, flattened, taken by id.
type Take = Box<dyn Fn(&mut <A as AutodiffBackend>::Gradients) -> Option<Vec<f32>> + Send + Sync>;

struct Takers(HashMap<ParamId, Take>);

impl ModuleVisitor<A> for Takers {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<A, D>>) {
        let t = param.val();
        let take: Take = Box::new(move |g| {
            t.grad_remove(g).map(|x| {
                x.flatten::<1>(0, D - 1)
                    .into_data()
                    .to_vec::<f32>()
                    .unwrap_or_default()
            })
        });
        self.0.insert(param.id, take);
    }
}

/// Takes each point's group at the point; records the order and what was missing.
struct Hook {
    groups: Vec<Vec<ParamId>>,
    takers: Takers,
    fired: Mutex<Vec<usize>>,
    taken: Mutex<HashMap<ParamId, Vec<f32>>>,
    missing: Mutex<Vec<ParamId>>,
}

impl ReadyHook<A> for Hook {
    fn ready(&self, point: usize, grads: &mut <A as AutodiffBackend>::Gradients) {
        self.fired.lock().unwrap().push(point);
        for id in &self.groups[point] {
            match self.takers.0.get(id).and_then(|t| t(grads)) {
                Some(g) => {
                    self.taken.lock().unwrap().insert(*id, g);
                }
                None => self.missing.lock().unwrap().push(*id),
            }
        }
    }
}

#[test]
fn each_block_point_hands_over_its_blocks_complete_gradients_deepest_first() {
    let m = model::<A>();
    let spec = spec();
    let ids: Tensor<A, 3, Int> = Tensor::from_data(
        TensorData::new(tokens(&spec, 2, 3, 7), [2, 3, spec.n]),
        &Default::default(),
    );
    let options = LossOptions {
        ego_weight: 1.0,
        prior_drop: 0.0,
        ordinal_sigma: 0.0,
        kernels: Default::default(),
    };
    let mut plain = m.loss_with(ids.clone(), options).unwrap().total.backward();
    let mut takers = Takers(HashMap::new());
    m.visit(&mut takers);
    let hook = Arc::new(Hook {
        groups: m.ready_groups(),
        takers,
        fired: Mutex::new(Vec::new()),
        taken: Mutex::new(HashMap::new()),
        missing: Mutex::new(Vec::new()),
    });
    let points = ReadyPoints::new::<A>(hook.clone());
    let mut marked = m
        .loss_marked(ids, options, Some(&points))
        .unwrap()
        .total
        .backward();

    // Two TAR blocks (points 0, 1), two OAR blocks (points 2, 3): the OAR's last block is deepest.
    assert_eq!(*hook.fired.lock().unwrap(), vec![3, 2, 1, 0]);
    assert!(hook.missing.lock().unwrap().is_empty());
    let taken = hook.taken.lock().unwrap();
    let grouped: usize = m.ready_groups().iter().map(Vec::len).sum();
    assert_eq!(taken.len(), grouped);
    assert!(grouped > 0);
    let mut all = Takers(HashMap::new());
    m.visit(&mut all);
    for (id, take) in &all.0 {
        let reference = take(&mut plain);
        let left = take(&mut marked);
        match taken.get(id) {
            // A block's parameter: taken at its point, nothing arrives after, same values as unmarked.
            Some(g) => {
                assert!(left.is_none(), "{id}: gradient after its point");
                let r = reference.unwrap();
                let scale = r.iter().fold(0f32, |a, x| a.max(x.abs())).max(1e-6);
                let worst = g.iter().zip(&r).fold(0f32, |a, (x, y)| a.max((x - y).abs()));
                assert!(worst <= 1e-5 * scale, "{id}: {worst} against {scale}");
            }
            // The rest stays for the end of the backward pass.
            None => assert_eq!(left.is_some(), reference.is_some(), "{id}"),
        }
    }
}
