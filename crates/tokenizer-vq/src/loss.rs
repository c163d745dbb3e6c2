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
    /// Weighted sum.
    pub total: Tensor<B, 1>,
    /// Named unweighted parts, for logs.
    pub parts: Vec<(&'static str, Tensor<B, 1>)>,
}

/// The reconstruction loss of `recon` against `target` `[B, C, H, W]` (targets in {0, 1} for binary
/// output, [-1, 1] for RGB).
pub fn reconstruction<B: Backend>(
    out: Output,
    cfg: &LossConfig,
    recon: Tensor<B, 4>,
    target: Tensor<B, 4>,
) -> LossParts<B> {
    match out {
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
            let inter = (p.clone() * target.clone()).sum_dims(&[0, 2, 3]);
            let denom = p.sum_dims(&[0, 2, 3]) + target.sum_dims(&[0, 2, 3]);
            let dice = (inter.mul_scalar(2.0).add_scalar(1.0) / denom.add_scalar(1.0))
                .neg()
                .add_scalar(1.0)
                .mean();
            let total = bce.clone().mul_scalar(cfg.bce) + dice.clone().mul_scalar(cfg.dice);
            LossParts {
                total,
                parts: vec![("bce", bce), ("dice", dice)],
            }
        }
        Output::Rgb => {
            let d = recon - target;
            let l1 = d.clone().abs().mean();
            let l2 = d.powf_scalar(2.0).mean();
            let total = l1.clone().mul_scalar(cfg.l1) + l2.clone().mul_scalar(cfg.l2);
            LossParts {
                total,
                parts: vec![("l1", l1), ("l2", l2)],
            }
        }
    }
}

/// Commitment: squared distance between unit encoder outputs and their (fixed) codes.
pub fn commitment<B: Backend>(z: Tensor<B, 2>, z_q: Tensor<B, 2>) -> Tensor<B, 1> {
    (z - z_q.detach()).powf_scalar(2.0).sum_dim(1).mean()
}
