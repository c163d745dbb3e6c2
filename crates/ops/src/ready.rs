//! Points in the forward pass where, going backwards, a group of parameters' gradients is complete: what
//! lets data parallelism start a bucket's all-reduce while the rest of the backward pass still runs (as
//! PyTorch's DDP does with its per-parameter hooks).
//!
//! burn's backward pass runs its steps deepest first (by distance from the leaves), not in reverse order
//! of creation, so a hook on a parameter itself (depth 1) would run last. A point is instead an identity
//! operation on an activation `x` ([`ReadyPoints::mark`]): its backward step has `x`'s depth plus one, so
//! it runs once every operation that read the marked tensor, directly or not, has passed its gradients
//! on. A block whose parameters are read only by operations on its marked input has every parameter's
//! gradient complete when its point runs. The hook ([`ReadyHook`]) then takes those gradients out of the
//! backward pass's container.
//!
//! The operation is recognised on `Autodiff<Flex>` and `Autodiff<Cuda>` (either checkpointing strategy);
//! on any other backend, or with a hook made for another backend, [`ReadyPoints::mark`] returns `x`
//! unchanged and the gradients simply stay in the container for the end of the backward pass.

use crate::dispatch::same;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Tensor, TensorPrimitive};
use std::any::Any;
use std::sync::Arc;

/// What runs when the backward pass passes a point.
pub trait ReadyHook<B: AutodiffBackend>: Send + Sync {
    /// The backward pass has passed `point`: the gradients of the parameters read only after it in the
    /// forward pass are complete in `grads` (take them with `Tensor::grad_remove`).
    fn ready(&self, point: usize, grads: &mut B::Gradients);
}

/// A [`ReadyHook`] for the forward passes of one backend, to hand to a model generic over its backend.
#[derive(Clone)]
pub struct ReadyPoints {
    /// An `Arc<dyn ReadyHook<B>>` for the `B` given to [`ReadyPoints::new`].
    hook: Arc<dyn Any + Send + Sync>,
}

impl std::fmt::Debug for ReadyPoints {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ReadyPoints")
    }
}

type MarkFn<B, const D: usize> = fn(&ReadyPoints, Tensor<B, D>, usize) -> Tensor<B, D>;

impl ReadyPoints {
    /// Points that call `hook` on backend `B`.
    pub fn new<B: AutodiffBackend>(hook: Arc<dyn ReadyHook<B>>) -> Self {
        Self { hook: Arc::new(hook) }
    }

    /// `x`, marked as point `point`: the hook runs for `point` once the backward pass has passed every
    /// operation that read the result. Unmarked (`x` itself) where the backend is not a recognised
    /// training backend or the hook was made for another.
    pub fn mark<B: Backend, const D: usize>(&self, x: Tensor<B, D>, point: usize) -> Tensor<B, D> {
        match marker::<B, D>() {
            Some(apply) => apply(self, x, point),
            None => x,
        }
    }
}

/// The marking operation where `B` is `Autodiff<Flex>` or `Autodiff<Cuda>`.
fn marker<B: Backend, const D: usize>() -> Option<MarkFn<B, D>> {
    let found = on::<B, burn::backend::Flex, D>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(|| on::<B, burn::backend::Cuda, D>());
    found
}

fn on<B: Backend, I: Backend, const D: usize>() -> Option<MarkFn<B, D>> {
    let plain: MarkFn<Autodiff<I>, D> = apply::<I, NoCheckpointing, D>;
    let balanced: MarkFn<Autodiff<I, BalancedCheckpointing>, D> = apply::<I, BalancedCheckpointing, D>;
    same(plain).or_else(|| same(balanced))
}

/// The backward step of a point.
struct Point<I: Backend, C: CheckpointStrategy> {
    hook: Arc<dyn ReadyHook<Autodiff<I, C>>>,
    point: usize,
}

impl<I: Backend, C: CheckpointStrategy> std::fmt::Debug for Point<I, C> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ReadyPoint({})", self.point)
    }
}

impl<I: Backend, C: CheckpointStrategy> Backward<I, 1> for Point<I, C> {
    type State = ();

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let g = grads.consume::<I>(&ops.node);
        // `Autodiff<I, C>`'s gradients are this container.
        self.hook.ready(self.point, grads);
        if let [Some(parent)] = &ops.parents {
            grads.register::<I>(parent.id, g);
        }
    }
}

fn apply<I: Backend, C: CheckpointStrategy, const D: usize>(
    points: &ReadyPoints,
    x: Tensor<Autodiff<I, C>, D>,
    point: usize,
) -> Tensor<Autodiff<I, C>, D> {
    let Some(hook) = points.hook.downcast_ref::<Arc<dyn ReadyHook<Autodiff<I, C>>>>() else {
        return x;
    };
    let x = x.into_primitive().tensor();
    let out = Point {
        hook: hook.clone(),
        point,
    }
    .prepare::<C>([x.node.clone()])
    .compute_bound()
    .stateless(x.primitive.clone());
    Tensor::from_primitive(TensorPrimitive::Float(out))
}

#[cfg(test)]
mod tests;
