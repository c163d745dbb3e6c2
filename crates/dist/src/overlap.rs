//! Gradient averaging that overlaps the backward pass: each bucket's all-reduce starts as soon as the
//! backward pass has completed its gradients, as PyTorch's DDP reducer does.
//!
//! The model marks points in its forward pass (`umgen_ops::ready`) and says which parameters' gradients
//! each point completes. [`Overlap`] is the hook: when the backward pass passes a point it takes those
//! gradients out of the backward pass's container (adding what earlier accumulation micro-steps left),
//! and once a bucket's worth has gathered it starts the bucket's all-reduce. On a group that can start
//! a collective without waiting ([`AsyncCollective`], NCCL) the all-reduce is queued on its own stream behind
//! the kernels that produced the bucket, and the backward pass's remaining kernels run beside it; other
//! groups reduce the gathered buckets in the same order after the backward pass. [`Overlap::finish`]
//! reduces the parameters no point completed (the embeddings, heads and norms around the blocks),
//! orders everything after the collectives, and hands the averaged gradients to the optimizer.
//!
//! Every rank runs the same forward pass, so the points fire in the same order everywhere and every rank
//! starts the same collectives on buffers of the same length, in the same order.

use crate::error::{DistError, Result};
use crate::grads::{as_one, buckets, register, take_flat};
use crate::group::{AsyncCollective, ProcessGroup};
use burn::module::{AutodiffModule, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use umgen_ops::ready::{ReadyHook, ReadyPoints};

type Inner<B> = <B as AutodiffBackend>::InnerBackend;
type Grads<B> = <B as AutodiffBackend>::Gradients;

/// Takes one parameter's gradient, flattened, out of the backward pass's container.
type Take<B> = Box<dyn Fn(&mut Grads<B>) -> Option<Tensor<Inner<B>, 1>> + Send + Sync>;

/// A float parameter: its id, shape, and how to take its gradient.
struct Entry<B: AutodiffBackend> {
    id: ParamId,
    shape: Vec<usize>,
    take: Take<B>,
}

struct Entries<B: AutodiffBackend>(Vec<Entry<B>>);

impl<B: AutodiffBackend> ModuleVisitor<B> for Entries<B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let t = param.val();
        self.0.push(Entry {
            id: param.id,
            shape: t.dims().to_vec(),
            take: Box::new(move |g| t.grad_remove(g).map(|x| x.flatten::<1>(0, D - 1))),
        });
    }
}

/// A bucket: the parameters it holds (indices into the entries, in order) and their flat gradients, the
/// all-reduce's (unsettled) results where it was started.
struct Bucket<B: AutodiffBackend> {
    params: Vec<usize>,
    parts: Vec<Tensor<Inner<B>, 1>>,
    started: bool,
}

/// What the hook gathers during one backward pass.
struct State<B: AutodiffBackend> {
    entries: Vec<Entry<B>>,
    /// Per point, the entries it completes.
    points: Vec<Vec<usize>>,
    fired: Vec<bool>,
    /// Gradients of earlier accumulation micro-steps, added before the reduction.
    prior: GradientsParams,
    /// Entries already taken (by a point) and their flat gradients, waiting for a bucket.
    gathered: Vec<(usize, Tensor<Inner<B>, 1>)>,
    gathered_elems: usize,
    taken: Vec<bool>,
    buckets: Vec<Bucket<B>>,
    bucket_elems: usize,
    device: burn::tensor::Device<Inner<B>>,
    starter: Option<Arc<dyn AsyncCollective<Inner<B>>>>,
    /// The first failure of a started collective (reported by [`Overlap::finish`]).
    error: Option<DistError>,
}

impl<B: AutodiffBackend> State<B> {
    /// Entry `i`'s gradient: the backward pass's (if any) plus the earlier micro-steps' (if any), zeros
    /// where neither exists (every rank must reduce the same buffers).
    fn gradient(&mut self, i: usize, grads: &mut Grads<B>) -> Tensor<Inner<B>, 1> {
        let e = &self.entries[i];
        let now = (e.take)(grads);
        let before = take_flat::<B>(&mut self.prior, e.id, e.shape.len());
        match (now, before) {
            (Some(a), Some(b)) => a + b,
            (Some(a), None) | (None, Some(a)) => a,
            (None, None) => Tensor::zeros([e.shape.iter().product::<usize>()], &self.device),
        }
    }

    fn gather(&mut self, i: usize, grads: &mut Grads<B>) {
        let g = self.gradient(i, grads);
        self.gathered_elems += g.dims()[0];
        self.gathered.push((i, g));
        self.taken[i] = true;
    }

    /// Turns the gathered gradients into a bucket, started where the group can start one (one collective
    /// launch for the bucket's tensors as they lie: no copy into a flat buffer and out again).
    fn close_bucket(&mut self) {
        if self.gathered.is_empty() {
            return;
        }
        let (params, parts): (Vec<usize>, Vec<_>) = std::mem::take(&mut self.gathered).into_iter().unzip();
        self.gathered_elems = 0;
        let (parts, started) = match (&self.starter, &self.error) {
            (Some(s), None) => match s.start_mean(parts.iter().cloned().map(raw).collect()) {
                Ok(t) => (t.into_iter().map(typed).collect(), true),
                Err(e) => {
                    self.error = Some(e);
                    (parts, false)
                }
            },
            _ => (parts, false),
        };
        self.buckets.push(Bucket {
            params,
            parts,
            started,
        });
    }
}

/// The hook of one data-parallel backward pass ([module docs](self)).
pub struct Overlap<B: AutodiffBackend> {
    state: Shared<B>,
}

/// The state, which [`Overlap::finish`] takes out: points that run later (a graph kept past its backward
/// pass) find nothing to do.
type Shared<B> = Arc<Mutex<Option<State<B>>>>;

/// The hook as the backward pass calls it.
struct Hook<B: AutodiffBackend>(Shared<B>);

impl<B: AutodiffBackend> ReadyHook<B> for Hook<B> {
    fn ready(&self, point: usize, grads: &mut Grads<B>) {
        let Ok(mut guard) = self.0.lock() else { return };
        let Some(st) = guard.as_mut() else { return };
        if st.fired.get(point).copied() != Some(false) {
            return;
        }
        st.fired[point] = true;
        for i in st.points[point].clone() {
            if !st.taken[i] {
                st.gather(i, grads);
            }
        }
        if st.gathered_elems >= st.bucket_elems {
            st.close_bucket();
        }
    }
}

impl<B: AutodiffBackend> Overlap<B> {
    /// The hook for a backward pass of `model` whose points complete `points` (parameter ids per point,
    /// e.g. `Backbone::ready_groups`), with `prior` the gradients of earlier accumulation micro-steps,
    /// in buckets of about `bucket_bytes`.
    pub fn new<M: AutodiffModule<B>>(
        model: &M,
        points: &[Vec<ParamId>],
        prior: GradientsParams,
        group: &dyn ProcessGroup<Inner<B>>,
        bucket_bytes: usize,
    ) -> Self {
        let mut entries = Entries::<B>(Vec::new());
        model.visit(&mut entries);
        let entries = entries.0;
        let index: HashMap<ParamId, usize> = entries.iter().enumerate().map(|(i, e)| (e.id, i)).collect();
        let points: Vec<Vec<usize>> = points
            .iter()
            .map(|ids| ids.iter().filter_map(|id| index.get(id).copied()).collect())
            .collect();
        let n = entries.len();
        let state = State {
            fired: vec![false; points.len()],
            points,
            prior,
            gathered: Vec::new(),
            gathered_elems: 0,
            taken: vec![false; n],
            buckets: Vec::new(),
            bucket_elems: (bucket_bytes / 4).max(1),
            device: model.devices().into_iter().next().unwrap_or_default(),
            starter: group.async_collective(),
            error: None,
            entries,
        };
        Self {
            state: Arc::new(Mutex::new(Some(state))),
        }
    }

    /// The points to mark the forward pass with.
    pub fn points(&self) -> ReadyPoints {
        ReadyPoints::new::<B>(Arc::new(Hook(self.state.clone())))
    }

    /// The averaged gradients of every parameter, after the backward pass returned `grads`: reduces
    /// what no point took (in module order, in buckets), reduces the gathered buckets on a group that
    /// did not start them, and orders every reader of the results after the collectives. A gradient
    /// that reaches a parameter after its point took it is an error naming the parameter (the model
    /// reads it outside the block it declared it in).
    pub fn finish(
        self,
        mut grads: Grads<B>,
        group: &mut dyn ProcessGroup<Inner<B>>,
    ) -> Result<GradientsParams> {
        let taken = match self.state.lock() {
            Ok(mut s) => s.take(),
            Err(_) => None,
        };
        let Some(mut st) = taken else {
            return Err(collective_error(group, "the gradient hook panicked"));
        };
        if let Some(e) = st.error.take() {
            return Err(e);
        }
        for (i, e) in st.entries.iter().enumerate() {
            if st.taken[i] && (e.take)(&mut grads).is_some() {
                let why = format!(
                    "parameter {} (shape {:?}) received gradient after its ready point had reduced it: the model reads it outside its block",
                    e.id, e.shape
                );
                return Err(collective_error(group, &why));
            }
        }
        st.close_bucket();
        // The parameters no point completed, in module order.
        let rest: Vec<usize> = (0..st.entries.len()).filter(|&i| !st.taken[i]).collect();
        let sizes: Vec<usize> = rest
            .iter()
            .map(|&i| st.entries[i].shape.iter().product())
            .collect();
        for range in buckets(&sizes, st.bucket_elems) {
            for &i in &rest[range] {
                st.gather(i, &mut grads);
            }
            st.close_bucket();
        }
        if let Some(e) = st.error.take() {
            return Err(e);
        }
        let buckets = std::mem::take(&mut st.buckets);
        // Each bucket's gradients, averaged: started ones settled at once, the others reduced here as one
        // flat buffer each.
        let mut started = Vec::new();
        let mut reduced: Vec<Option<Vec<Tensor<Inner<B>, 1>>>> = Vec::with_capacity(buckets.len());
        for b in &buckets {
            if b.started {
                started.extend(b.parts.iter().cloned());
                reduced.push(None);
            } else {
                let parts = as_one(b.parts.clone(), &mut |t| group.all_reduce_mean(t))?;
                reduced.push(Some(parts));
            }
        }
        let mut settled = match (&st.starter, started.is_empty()) {
            (Some(s), false) => s
                .settle(started.into_iter().map(raw).collect())?
                .into_iter()
                .map(typed)
                .collect::<Vec<_>>()
                .into_iter(),
            _ => Vec::new().into_iter(),
        };
        let mut out = GradientsParams::new();
        for (b, parts) in buckets.iter().zip(reduced) {
            let parts = match parts {
                Some(p) => p,
                None => settled.by_ref().take(b.params.len()).collect(),
            };
            if parts.len() != b.params.len() {
                return Err(collective_error(group, "a started all-reduce was not settled"));
            }
            for (&i, t) in b.params.iter().zip(parts) {
                let e = &st.entries[i];
                register::<B>(&mut out, e.id, t, &e.shape);
            }
        }
        Ok(out)
    }
}

/// A flat tensor as the started collectives take it.
fn raw<B: burn::tensor::backend::Backend>(t: Tensor<B, 1>) -> FloatTensor<B> {
    t.into_primitive().tensor()
}

/// A started collective's flat result as a tensor.
fn typed<B: burn::tensor::backend::Backend>(t: FloatTensor<B>) -> Tensor<B, 1> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

fn collective_error<B: burn::tensor::backend::Backend>(
    group: &dyn ProcessGroup<B>,
    reason: &str,
) -> DistError {
    DistError::Collective {
        rank: group.rank(),
        op: "all-reduce",
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests;
