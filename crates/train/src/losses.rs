//! A step's losses on the device, and their read-back on logging steps.

use crate::error::Result;
use burn::tensor::Tensor;
use burn::tensor::backend::AutodiffBackend;
use umgen_dist::ProcessGroup;

/// Named values of a logging step, the total loss first.
pub(crate) type Logged = Vec<(String, f64)>;

/// `[1 + L]`: the step's total loss and its L terms, each the mean over the micro-batches, on the device.
pub(crate) fn step_losses<B: AutodiffBackend>(
    parts: &[umgen_backbone::Losses<B>],
) -> Tensor<B::InnerBackend, 1> {
    let micro: Vec<Tensor<B::InnerBackend, 1>> = parts
        .iter()
        .map(|l| {
            let v = std::iter::once(l.total.clone()).chain(l.parts.iter().map(|(_, t)| t.clone()));
            Tensor::cat(v.map(|t| t.inner()).collect(), 0)
        })
        .collect();
    let width = micro.first().map_or(0, |m| m.dims()[0]);
    let n = micro.len();
    Tensor::cat(micro, 0)
        .reshape([n, width])
        .mean_dim(0)
        .reshape([width])
}

/// Mean over micro-batches and ranks of every loss part and the gradient norm (equal on every rank), fetched
/// from the device in one transfer, then `lr`, `grad_norm`. The first entry is the total loss.
pub(crate) fn averaged_parts<B: AutodiffBackend>(
    parts: &[umgen_backbone::Losses<B>],
    group: &mut dyn ProcessGroup<B::InnerBackend>,
    lr: f64,
    grad_norm: Tensor<B::InnerBackend, 1>,
    extra: Tensor<B::InnerBackend, 1>,
) -> Result<(Logged, Vec<f64>)> {
    let Some(first) = parts.first() else {
        return Ok((Vec::new(), Vec::new()));
    };
    let mut names = vec!["loss".to_string()];
    names.extend(first.parts.iter().map(|(k, _)| k.clone()));
    let tensors: Vec<Tensor<B, 1>> = parts
        .iter()
        .flat_map(|l| std::iter::once(l.total.clone()).chain(l.parts.iter().map(|(_, t)| t.clone())))
        .collect();
    let main = tensors.len() + 1;
    let local = Tensor::cat(vec![Tensor::cat(tensors, 0).inner(), grad_norm, extra], 0);
    let mut values: Vec<f64> = group.all_reduce_mean(local)?.into_data().iter::<f64>().collect();
    let extra = values.split_off(main.min(values.len()));
    let grad_norm = values.pop().unwrap_or(f64::NAN);
    let k = names.len();
    let mut out: Vec<(String, f64)> = names
        .into_iter()
        .enumerate()
        .map(|(i, name)| {
            (
                name,
                (0..parts.len()).map(|m| values[m * k + i]).sum::<f64>() / parts.len() as f64,
            )
        })
        .collect();
    out.extend([("lr".into(), lr), ("grad_norm".into(), grad_norm)]);
    Ok((out, extra))
}
