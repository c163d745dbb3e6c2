//! Validation during training (`train.val_every`): the losses of a fixed set of windows of another split
//! (the held-out network of the bundled sample, say), computed without dropout or `prior_drop`, so that a
//! run shows when what it learns stops carrying over to scenes it never trains on.

use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use burn::module::AutodiffModule;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Int, Tensor, TensorData};
use umgen_backbone::{Backbone, LossOptions};
use umgen_data::{TokenSet, Window};

/// The windows a run validates on, and how it batches them.
#[derive(Debug, Clone)]
pub(crate) struct Validation {
    windows: Vec<Window>,
    every: u64,
    batch: usize,
    frames: usize,
    gap: usize,
}

impl Validation {
    /// The validation of a run whose windows hold `frames` frames; `None` when `train.val_every` is 0.
    /// A split without such windows in the token cache is an error naming `train.val_split`.
    pub(crate) fn new(tc: &TrainConfig, tokens: &TokenSet, frames: usize) -> Result<Option<Self>> {
        if tc.val_every == 0 {
            return Ok(None);
        }
        let all = tokens.windows(frames, tc.gap, Some(&tc.val_split));
        if all.is_empty() {
            return Err(TrainError::Setup(format!(
                "train.val_split = \"{}\": no windows of {frames} frames at gap {} in the token cache (set \
                 train.data so that umgen train tokenizes the split, or train.val_every = 0)",
                tc.val_split, tc.gap
            )));
        }
        Ok(Some(Self {
            windows: spread(&all, tc.val_windows),
            every: tc.val_every,
            batch: tc.batch_size,
            frames,
            gap: tc.gap,
        }))
    }

    /// Windows scored in a pass.
    pub(crate) fn len(&self) -> usize {
        self.windows.len()
    }

    /// Whether the run validates after `step` of `steps`.
    pub(crate) fn due(&self, step: u64, steps: u64) -> bool {
        step.is_multiple_of(self.every) || step == steps
    }

    /// The losses of `model` (its inference copy: no dropout) over the windows, `prior_drop` off, each a
    /// mean over the windows: `val/loss` first, then `val/<part>` for each part of the training loss.
    pub(crate) fn losses<B: AutodiffBackend>(
        &self,
        model: &Backbone<B>,
        tokens: &TokenSet,
        opts: LossOptions,
        device: &B::Device,
    ) -> Result<Vec<(String, f64)>> {
        let model = model.valid();
        let opts = LossOptions {
            prior_drop: 0.0,
            ..opts
        };
        let n = model.spec().n;
        let picks: Vec<usize> = (0..self.windows.len()).collect();
        let mut names: Vec<String> = Vec::new();
        let mut sums: Vec<f64> = Vec::new();
        for chunk in picks.chunks(self.batch.max(1)) {
            let batch = load_batch::<B::InnerBackend>(
                tokens,
                &self.windows,
                chunk,
                self.frames,
                self.gap,
                n,
                device,
            )?;
            let l = model.loss_with(batch, opts)?;
            if names.is_empty() {
                names.push("val/loss".into());
                names.extend(l.parts.iter().map(|(k, _)| format!("val/{k}")));
                sums = vec![0.0; names.len()];
            }
            let values = Tensor::cat(
                std::iter::once(l.total)
                    .chain(l.parts.into_iter().map(|(_, t)| t))
                    .collect(),
                0,
            );
            // Each batch's losses are means over its windows: weighted by their count, the sum over
            // batches divided by the windows is the mean over windows.
            for (s, v) in sums.iter_mut().zip(values.into_data().iter::<f64>()) {
                *s += v * chunk.len() as f64;
            }
        }
        let count = self.windows.len() as f64;
        Ok(names.into_iter().zip(sums).map(|(k, s)| (k, s / count)).collect())
    }
}

/// `count` of `windows` spread evenly over them (all of them when there are no more than `count`), in
/// their order.
fn spread(windows: &[Window], count: usize) -> Vec<Window> {
    if windows.len() <= count {
        return windows.to_vec();
    }
    (0..count).map(|i| windows[i * windows.len() / count]).collect()
}

/// The token ids `[picks, f, n]` of the windows `picks` of `windows`, on `device`.
pub(crate) fn load_batch<B: Backend>(
    tokens: &TokenSet,
    windows: &[Window],
    picks: &[usize],
    f: usize,
    gap: usize,
    n: usize,
    device: &B::Device,
) -> Result<Tensor<B, 3, Int>> {
    let mut ids = Vec::with_capacity(picks.len() * f * n);
    for &p in picks {
        ids.extend(tokens.read(windows[p], f, gap)?.into_iter().map(i64::from));
    }
    Ok(Tensor::from_data(
        TensorData::new(ids, [picks.len(), f, n]),
        device,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_spread_evenly_and_all_when_few() {
        let w: Vec<Window> = (0..10)
            .map(|i| Window {
                clip: i / 4,
                start: i % 4,
            })
            .collect();
        assert_eq!(spread(&w, 20), w);
        assert_eq!(spread(&w, 10), w);
        // 10 windows, 4 picks: indices 0, 2, 5, 7.
        let picked = spread(&w, 4);
        assert_eq!(picked, vec![w[0], w[2], w[5], w[7]]);
        assert_eq!(spread(&w, 1), vec![w[0]]);
    }
}
