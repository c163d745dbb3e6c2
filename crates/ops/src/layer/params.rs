//! A layer's parameters taken apart for the operation: each as a value on the inner backend (what the
//! passes compute with) and as the tracked tensor the model holds (the operation's parent, which gets the
//! gradient).

use super::LayerParts;
use super::math::{LayerBackend, Lin, Norm, Weights};
use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::module::Param;
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;
use burn::tensor::ops::FloatTensor;

/// A parameter as the autodiff backend holds it (burn does not export its node type; the tensor carries it).
pub(super) type Node<I, C> = FloatTensor<Autodiff<I, C>>;

/// Tracked parameters in [`Weights`]' order.
pub(super) type Tracked<I, C> = Vec<Node<I, C>>;

/// A weight and its bias (or scale and shift) as tracked tensors.
type Two<I, C> = [Node<I, C>; 2];

/// A tracked parameter's value on the inner backend, and the parameter.
fn split<I: LayerBackend, C: CheckpointStrategy, const D: usize>(
    p: &Param<Tensor<Autodiff<I, C>, D>>,
) -> (Tensor<I, D>, Node<I, C>) {
    let t = p.val().into_primitive().tensor();
    (crate::format::float(t.primitive.clone()), t)
}

/// A layer norm's parameters on the inner backend and as tracked tensors; `None` without a shift.
fn norm<I: LayerBackend, C: CheckpointStrategy>(
    n: &LayerNorm<Autodiff<I, C>>,
) -> Option<(Norm<I>, Two<I, C>)> {
    let (gamma, ng) = split(&n.gamma);
    let (beta, nb) = split(n.beta.as_ref()?);
    Some((Norm { gamma, beta }, [ng, nb]))
}

/// A linear layer's parameters on the inner backend and as tracked tensors; `None` without a bias.
fn lin<I: LayerBackend, C: CheckpointStrategy>(l: &Linear<Autodiff<I, C>>) -> Option<(Lin<I>, Two<I, C>)> {
    let (w, nw) = split(&l.weight);
    let (b, nb) = split(l.bias.as_ref()?);
    Some((Lin { w, b }, [nw, nb]))
}

/// The layer's parameters on the inner backend and as tracked tensors, in [`Weights`]' order; `None` for a
/// layer without biases.
pub(super) fn weights<I: LayerBackend, C: CheckpointStrategy>(
    parts: &LayerParts<'_, Autodiff<I, C>>,
) -> Option<(Weights<I>, Tracked<I, C>)> {
    let (ln1, a) = norm(parts.ln1)?;
    let (ln_ctx, ctx) = match parts.ln_ctx {
        Some(n) => {
            let (n, t) = norm(n)?;
            (Some(n), Some(t))
        }
        None => (None, None),
    };
    let (q, b) = lin(parts.q)?;
    let (kv, c) = lin(parts.kv)?;
    let (proj, d) = lin(parts.proj)?;
    let (ln2, e) = norm(parts.ln2)?;
    let (fc, f) = lin(parts.fc)?;
    let (out, g) = lin(parts.out)?;
    let tracked = [Some(a), ctx, Some(b), Some(c), Some(d), Some(e), Some(f), Some(g)]
        .into_iter()
        .flatten()
        .flatten()
        .collect();
    Some((
        Weights {
            ln1,
            ln_ctx,
            q,
            kv,
            proj,
            ln2,
            fc,
            out,
        },
        tracked,
    ))
}
