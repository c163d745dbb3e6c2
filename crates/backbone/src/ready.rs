//! The backbone's ready points (`umgen_ops::ready`): the input of every TAR and OAR block, each with the
//! parameters of its block, whose gradients are complete once the backward pass has passed it.

use crate::model::Backbone;
use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// The point of TAR block `i`.
pub(crate) fn tar_point(i: usize) -> usize {
    i
}

/// The ids of a module's float parameters, in module order.
struct Ids(Vec<ParamId>);

impl<B: Backend> ModuleVisitor<B> for Ids {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        self.0.push(param.id);
    }
}

fn ids<B: Backend, M: Module<B>>(m: &M) -> Vec<ParamId> {
    let mut v = Ids(Vec::new());
    m.visit(&mut v);
    v.0
}

impl<B: Backend> Backbone<B> {
    /// The point of OAR block `i`.
    pub(crate) fn oar_point(&self, i: usize) -> usize {
        self.tar_blocks().len() + i
    }

    /// The parameters whose gradients are complete at each ready point, indexed by point: TAR block
    /// `i`'s at point `i`, then OAR block `j`'s at point `tar blocks + j`. Each block's parameters are
    /// read only by operations on the block's marked input; the rest of the model (embeddings, ego
    /// module, norms, heads) is at no point.
    pub fn ready_groups(&self) -> Vec<Vec<ParamId>> {
        let tar = self.tar_blocks().iter().map(|b| ids::<B, _>(b));
        let oar = self.oar_blocks().iter().map(|b| ids::<B, _>(b));
        tar.chain(oar).collect()
    }
}
