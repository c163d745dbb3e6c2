//! The backbone's ready points (`umgen_ops::ready`): the input of every TAR and OAR block, each with the
//! parameters of its block, whose gradients are complete once the backward pass has passed it
//! (`Backbone::ready_groups`).

use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// The point of TAR block `i`.
pub(crate) fn tar_point(i: usize) -> usize {
    i
}

/// The point of OAR block `i` after `tar_blocks` TAR blocks.
pub(crate) fn oar_point(tar_blocks: usize, i: usize) -> usize {
    tar_blocks + i
}

/// Collects parameter ids.
struct Ids(Vec<ParamId>);

impl<B: Backend> ModuleVisitor<B> for Ids {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        self.0.push(param.id);
    }
}

/// The ids of `m`'s float parameters, in module order.
pub(crate) fn ids<B: Backend, M: Module<B>>(m: &M) -> Vec<ParamId> {
    let mut v = Ids(Vec::new());
    m.visit(&mut v);
    v.0
}
