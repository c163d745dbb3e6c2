//! The training attention with keys and values as one tensor `[b, lk, 2d]` (a layer's kv product), so
//! that their gradient comes back as one tensor too.
//!
//! With keys and values split off `kv` before the attention operation, burn's autodiff gave `kv` its
//! gradient as two zero tensors, each with one half slice-assigned from the merged head layout, and their
//! sum: about 1.1 ms of each `small` attention layer's backward pass on an H100 (docs/decisions/005-training-attention-flash2.md).
//! Here the operation's parents are the queries and `kv`; keys and values are split into heads as views
//! on the inner backend, run through the same [`FusedAttention`] passes as [`super::tiled_autodiff`], and
//! the backward pass writes `dk` and `dv` into one `[b, lk, 2d]` gradient (one copy each).

use crate::dispatch::same;
use crate::flash::FusedAttention;
use crate::format::{Precision, float};
use crate::heads::split_kv;
use crate::kernels::Kernels;
use crate::tiled::operands;
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;

/// The operation on `B`: queries `[b, h, lq, dh]`, `kv` `[b, lk, 2·h·dh]`, causal, the products' format,
/// the kernels.
pub(crate) type KvFn<B> = fn(Tensor<B, 4>, Tensor<B, 3>, bool, Precision, &Kernels) -> Tensor<B, 4>;

/// The operation when `B` is a training backend.
pub(crate) fn kv_for<B: Backend>() -> Option<KvFn<B>> {
    let found = on::<B, burn::backend::Flex>();
    #[cfg(feature = "cuda")]
    let found = found.or_else(on::<B, burn::backend::Cuda>);
    found
}

fn on<B: Backend, I: FusedAttention>() -> Option<KvFn<B>> {
    let plain: KvFn<Autodiff<I, NoCheckpointing>> = apply::<I, NoCheckpointing>;
    let balanced: KvFn<Autodiff<I, BalancedCheckpointing>> = apply::<I, BalancedCheckpointing>;
    same(plain).or_else(|| same(balanced))
}

#[derive(Debug)]
struct KvAttention;

/// q, k, v (in the products' format), output, log-sum-exp; causal, the products' format, the kernels.
type Kept<B> = ([FloatTensor<B>; 5], bool, Precision, Kernels);

impl<B: FusedAttention> Backward<B, 2> for KvAttention {
    type State = Kept<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [nq, nkv] = ops.parents;
        let dout = float::<B, 4>(grads.consume::<B>(&ops.node));
        let ([q, k, v, out, lse], causal, precision, kernels) = ops.state;
        let (dq, dkv) = B::attention_backward_kv(
            float(q),
            float(k),
            float(v),
            float(out),
            float(lse),
            dout,
            causal,
            precision,
            &kernels,
        );
        if let Some(node) = nq {
            grads.register::<B>(node.id, dq.into_primitive().tensor());
        }
        if let Some(node) = nkv {
            grads.register::<B>(node.id, dkv.into_primitive().tensor());
        }
    }
}

/// The attention of `q` over the keys and values of `kv` as one operation on `Autodiff<I, C>`.
fn apply<I: FusedAttention, C: CheckpointStrategy>(
    q: Tensor<Autodiff<I, C>, 4>,
    kv: Tensor<Autodiff<I, C>, 3>,
    causal: bool,
    precision: Precision,
    kernels: &Kernels,
) -> Tensor<Autodiff<I, C>, 4> {
    let heads = q.dims()[1];
    let (q, kv) = (q.into_primitive().tensor(), kv.into_primitive().tensor());
    let prep = KvAttention
        .prepare::<C>([q.node.clone(), kv.node.clone()])
        .compute_bound()
        .stateful();
    let (k, v) = split_kv(float::<I, 3>(kv.primitive), heads);
    // Cast once here, as `tiled_autodiff` does: the backward pass keeps the operands in the products' format.
    let (qi, ki, vi) = operands(float::<I, 4>(q.primitive), k, v, precision);
    let (out, lse) = I::attention_forward(qi.clone(), ki.clone(), vi.clone(), causal, precision, kernels);
    let out_p = out.clone().into_primitive().tensor();
    let y = match prep {
        OpsKind::Tracked(prep) => {
            let prim = |t: Tensor<I, 4>| t.into_primitive().tensor();
            let kept = [prim(qi), prim(ki), prim(vi), prim(out), prim(lse)];
            prep.finish((kept, causal, precision, *kernels), out_p)
        }
        OpsKind::UnTracked(prep) => prep.finish(out_p),
    };
    float(y)
}
