//! Reconstruction losses.

use crate::config::{LossConfig, Output};
use burn::tensor::Tensor;
use burn::tensor::activation::sigmoid;
use burn::tensor::backend::Backend;

/// `log(1 + e^x)` without overflow.
pub fn softplus<B: Backend, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    x.clone().clamp_min(0.0) + x.abs().neg().exp().add_scalar(1.0).log()
}

/// The parts of a reconstruction loss, each a scalar tensor; `total` is their weighted sum.
#[derive(Debug, Clone)]
pub struct LossParts<B: Backend> {
    /// Weighted sum (over the global batch in a data-parallel run).
    pub total: Tensor<B, 1>,
    /// What this process differentiates: `total` alone, or in a data-parallel run the rank's share
    /// whose gradients, averaged over the ranks, are those of `total`.
    pub objective: Tensor<B, 1>,
    /// Named unweighted parts, for logs.
    pub parts: Vec<(&'static str, Tensor<B, 1>)>,
}

/// The reconstruction loss of `recon` against `target` `[B, C, H, W]` (targets in {0, 1} for binary
/// output, [-1, 1] for RGB), on one of `world` data-parallel ranks (1 alone). The means (BCE, L1, L2) average over ranks
/// by themselves; the Dice term is a ratio of sums over the whole batch, so the rank's per-channel sums
/// are completed with the other ranks' through `sum_ranks` (which returns a tensor summed over all
/// ranks) and enter `objective` scaled by the world size: the others' sums are constants here, so the
/// average of the ranks' gradients is the gradient of the global Dice.
pub fn reconstruction_over<B: Backend, E>(
    out: Output,
    cfg: &LossConfig,
    recon: Tensor<B, 4>,
    target: Tensor<B, 4>,
    world: usize,
    mut sum_ranks: impl FnMut(Tensor<B, 1>) -> Result<Tensor<B, 1>, E>,
) -> Result<LossParts<B>, E> {
    Ok(match out {
        Output::Binary => {
            // BCE with logits: y·softplus(-x)·w + (1 - y)·softplus(x), optionally focal.
            let pos = softplus(recon.clone().neg()) * target.clone();
            let neg = softplus(recon.clone()) * target.clone().neg().add_scalar(1.0);
            let mut bce = pos.mul_scalar(cfg.pos_weight) + neg;
            let p = sigmoid(recon);
            if cfg.focal_gamma > 0.0 {
                // (1 - p_t)^γ with p_t the probability of the true class.
                let pt = p.clone() * target.clone()
                    + (p.clone().neg().add_scalar(1.0)) * target.clone().neg().add_scalar(1.0);
                bce = bce * pt.neg().add_scalar(1.0).powf_scalar(cfg.focal_gamma);
            }
            let bce = bce.mean();
            // Soft Dice per channel over batch and pixels.
            let c = p.dims()[1];
            let mut inter = (p.clone() * target.clone()).sum_dims(&[0, 2, 3]).reshape([c]);
            let mut denom = (p.sum_dims(&[0, 2, 3]) + target.sum_dims(&[0, 2, 3])).reshape([c]);
            if world > 1 {
                let local = Tensor::cat(vec![inter.clone().detach(), denom.clone().detach()], 0);
                let others = sum_ranks(local.clone())? - local;
                inter = inter + others.clone().narrow(0, 0, c);
                denom = denom + others.narrow(0, c, c);
            }
            let dice = (inter.mul_scalar(2.0).add_scalar(1.0) / denom.add_scalar(1.0))
                .neg()
                .add_scalar(1.0)
                .mean();
            let total = bce.clone().mul_scalar(cfg.bce) + dice.clone().mul_scalar(cfg.dice);
            let objective =
                bce.clone().mul_scalar(cfg.bce) + dice.clone().mul_scalar(cfg.dice * world as f64);
            LossParts {
                total,
                objective,
                parts: vec![("bce", bce), ("dice", dice)],
            }
        }
        Output::Rgb => {
            let d = recon - target;
            let l1 = d.clone().abs().mean();
            let l2 = d.powf_scalar(2.0).mean();
            let total = l1.clone().mul_scalar(cfg.l1) + l2.clone().mul_scalar(cfg.l2);
            LossParts {
                objective: total.clone(),
                total,
                parts: vec![("l1", l1), ("l2", l2)],
            }
        }
    })
}

/// Commitment: squared distance between unit encoder outputs and their (fixed) codes.
pub fn commitment<B: Backend>(z: Tensor<B, 2>, z_q: Tensor<B, 2>) -> Tensor<B, 1> {
    (z - z_q.detach()).powf_scalar(2.0).sum_dim(1).mean()
}
