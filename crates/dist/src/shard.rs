//! Optimizer-state sharding (ZeRO stage 1): which rank updates which parameter ([`Shards`]), and the copy
//! of each updated parameter from the rank that owns it to every rank ([`Shards::gather`]).
//!
//! The unit is a whole parameter tensor, assigned largest first to the rank with the fewest elements so
//! far, as PyTorch's `ZeroRedundancyOptimizer` partitions: the shares then differ by less than one
//! tensor's size, and no tensor's update is split between kernels. Each rank keeps AdamW's moments for its
//! own parameters only. Gradients are still averaged over all ranks during the backward pass
//! ([`crate::Overlap`]), so each rank computes the global norm that clipping and the skip guard need from
//! the same values in the same order, with no collective of its own, and a sharded step updates every
//! parameter to the same bits as an unsharded one (docs/decisions/013-sharded-optimizer-state.md).

use crate::error::{DistError, Result};
use crate::grads::{Flat, Replace, as_one, buckets_of, shapes};
use crate::group::ProcessGroup;
use burn::module::{AutodiffModule, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};
use std::collections::{HashMap, HashSet};

type Inner<B> = <B as AutodiffBackend>::InnerBackend;

/// Which rank owns each float parameter of a model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Shards {
    rank: usize,
    world: usize,
    owners: HashMap<ParamId, usize>,
    /// Elements owned, per rank.
    loads: Vec<usize>,
}

/// A bucket of parameter copies holds at least this much (unless the parameters run out)...
const COPY_BUCKET_BYTES: usize = 256 << 20;
/// ... and at most this many tensors (one NCCL group each).
const COPY_BUCKET_TENSORS: usize = 256;

/// Float parameters' values as they lie (the backend's primitives), in module order.
struct Raw<B: AutodiffBackend>(Vec<FloatTensor<Inner<B>>>);

impl<B: AutodiffBackend> ModuleVisitor<B> for Raw<B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        self.0.push(param.val().inner().into_primitive().tensor());
    }
}

/// Replaces float parameters, in module order, with primitives of their own shapes.
struct ReplaceRaw<B: AutodiffBackend> {
    values: std::vec::IntoIter<FloatTensor<Inner<B>>>,
}

impl<B: AutodiffBackend> ModuleMapper<B> for ReplaceRaw<B> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        match self.values.next() {
            Some(v) => param.map(|t| {
                let grad = t.is_require_grad();
                let inner = Tensor::<Inner<B>, D>::from_primitive(TensorPrimitive::Float(v));
                Tensor::<B, D>::from_inner(inner).set_require_grad(grad)
            }),
            None => param,
        }
    }
}

/// Float parameters in module order: ids and element counts.
fn sizes<B: AutodiffBackend, M: AutodiffModule<B>>(model: &M) -> Vec<(ParamId, usize)> {
    shapes::<B, M>(model)
        .into_iter()
        .map(|(id, shape)| (id, shape.iter().product()))
        .collect()
}

impl Shards {
    /// The plan for `model`'s parameters over `world` ranks, as seen by `rank`: every rank that plans the
    /// same model gets the same owners.
    pub fn plan<B: AutodiffBackend, M: AutodiffModule<B>>(model: &M, rank: usize, world: usize) -> Self {
        Self::from_sizes(&sizes::<B, M>(model), rank, world)
    }

    /// The plan for parameters of the given sizes (module order breaks ties, then the lower rank).
    pub fn from_sizes(sizes: &[(ParamId, usize)], rank: usize, world: usize) -> Self {
        let world = world.max(1);
        let mut order: Vec<usize> = (0..sizes.len()).collect();
        // Stable: equal sizes keep module order.
        order.sort_by(|&a, &b| sizes[b].1.cmp(&sizes[a].1));
        let mut loads = vec![0usize; world];
        let mut owners = HashMap::with_capacity(sizes.len());
        for i in order {
            let (id, n) = sizes[i];
            let least = (0..world).min_by_key(|&r| (loads[r], r)).unwrap_or(0);
            loads[least] += n;
            owners.insert(id, least);
        }
        Self {
            rank,
            world,
            owners,
            loads,
        }
    }

    /// This rank.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// Number of ranks the parameters are shared out over.
    pub fn world(&self) -> usize {
        self.world
    }

    /// The rank that updates parameter `id` (`None` for a parameter the plan did not see).
    pub fn owner(&self, id: ParamId) -> Option<usize> {
        self.owners.get(&id).copied()
    }

    /// The parameters this rank updates.
    pub fn owned(&self) -> HashSet<ParamId> {
        self.owners
            .iter()
            .filter(|(_, r)| **r == self.rank)
            .map(|(id, _)| *id)
            .collect()
    }

    /// Parameter elements owned by each rank.
    pub fn loads(&self) -> &[usize] {
        &self.loads
    }

    /// `model` with every parameter's value taken from its owner, on every rank: after a step in which
    /// each rank updated only its own parameters. On a group that can start collectives without waiting
    /// the copies are queued behind the optimizer's kernels with no host wait, as the tensors lie, in a
    /// few large launches (the next forward pass needs them all, so small buckets would only cost the
    /// host more launches); elsewhere each owner's parameters go out as one flat buffer per bucket.
    pub fn gather<B: AutodiffBackend, M: AutodiffModule<B>>(
        &self,
        model: M,
        group: &mut dyn ProcessGroup<Inner<B>>,
    ) -> Result<M> {
        self.gather_in(model, group, COPY_BUCKET_BYTES, COPY_BUCKET_TENSORS)
    }

    /// [`Shards::gather`] in buckets of at least `bucket_bytes` (the last may be smaller) and at most
    /// `max_tensors` tensors.
    pub(crate) fn gather_in<B: AutodiffBackend, M: AutodiffModule<B>>(
        &self,
        model: M,
        group: &mut dyn ProcessGroup<Inner<B>>,
        bucket_bytes: usize,
        max_tensors: usize,
    ) -> Result<M> {
        if group.world_size() == 1 {
            return Ok(model);
        }
        if group.world_size() != self.world {
            let why = format!(
                "planned for {} ranks, the group has {}",
                self.world,
                group.world_size()
            );
            return Err(self.error(group, why));
        }
        let sizes = sizes::<B, M>(&model);
        let roots = sizes
            .iter()
            .map(|(id, _)| {
                self.owner(*id).ok_or_else(|| {
                    let why = format!("parameter {id} is in no shard: the plan was made for another model");
                    self.error(group, why)
                })
            })
            .collect::<Result<Vec<usize>>>()?;
        let elems: Vec<usize> = sizes.iter().map(|(_, n)| *n).collect();
        let ranges = buckets_of(&elems, bucket_bytes / 4, max_tensors);
        if let Some(starter) = group.async_collective() {
            let mut raw = Raw::<B>(Vec::new());
            model.visit(&mut raw);
            let mut parts = raw.0.into_iter();
            let mut started = Vec::with_capacity(elems.len());
            for range in ranges {
                let chunk: Vec<_> = parts.by_ref().take(range.len()).collect();
                started.extend(starter.start_broadcast(chunk, &roots[range])?);
            }
            let values = starter.settle(started)?;
            self.all_back(values.len(), elems.len(), group)?;
            return Ok(model.map(&mut ReplaceRaw::<B> {
                values: values.into_iter(),
            }));
        }
        let mut flat = Flat::<B> { values: Vec::new() };
        model.visit(&mut flat);
        let mut parts: Vec<Option<Tensor<Inner<B>, 1>>> = flat.values.into_iter().map(Some).collect();
        let mut out: Vec<Option<Tensor<Inner<B>, 1>>> = vec![None; parts.len()];
        for root in 0..self.world {
            let mine: Vec<usize> = (0..parts.len()).filter(|&i| roots[i] == root).collect();
            let sizes: Vec<usize> = mine.iter().map(|&i| elems[i]).collect();
            for range in buckets_of(&sizes, bucket_bytes / 4, max_tensors) {
                let at = &mine[range];
                let chunk: Vec<_> = at.iter().filter_map(|&i| parts[i].take()).collect();
                let copied = as_one(chunk, &mut |t| group.broadcast(t, root))?;
                for (&i, t) in at.iter().zip(copied) {
                    out[i] = Some(t);
                }
            }
        }
        let values: Vec<_> = out.into_iter().flatten().collect();
        self.all_back(values.len(), elems.len(), group)?;
        Ok(model.map(&mut Replace::<B> {
            values: values.into_iter(),
        }))
    }

    /// An error unless `got` values came back for the model's `want` parameters.
    fn all_back<B: burn::tensor::backend::Backend>(
        &self,
        got: usize,
        want: usize,
        group: &dyn ProcessGroup<B>,
    ) -> Result<()> {
        match got == want {
            true => Ok(()),
            false => Err(self.error(group, format!("{got} of {want} parameters came back"))),
        }
    }

    fn error<B: burn::tensor::backend::Backend>(
        &self,
        group: &dyn ProcessGroup<B>,
        reason: String,
    ) -> DistError {
        DistError::Collective {
            rank: group.rank(),
            op: "parameter all-gather",
            reason,
        }
    }
}

#[cfg(test)]
#[path = "shard/tests.rs"]
mod tests;
